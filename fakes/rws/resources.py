"""What the fake RWS controller serves, written from ABB's Robot Web Services manuals (RWS 1.0:
"Application manual - Robot Web Services", 3HAC050973-001, IRC5/RobotWare 6; RWS 2.0: the
OmniCore/RobotWare 7 reference) and from the robid RAPID module the README describes
("Driver abb_rws"). Nothing here comes from the daemon's driver.

RWS 1.0 names an action in the query (``?action=loadmod``) and answers JSON on ``?json=1``
(``{"_embedded": {"_state": [...]}}``); RWS 2.0 puts the action in the path
(``/rw/rapid/tasks/T_ROB1/loadmod``), wants the versioned media types
(``application/hal+json;v=2.0`` answers, ``application/x-www-form-urlencoded;v=2.0`` bodies,
``application/octet-stream;v=2.0`` or ``text/plain;v=2.0`` uploads) and answers
``{"state": [...]}``. Both subscribe with ``POST /subscription``
(``resources=1&1=<uri>&1-p=<0|1|2>``) and deliver events on a websocket (``/poll/<id>``;
subprotocol ``robapi2_subscription`` on 1.0, ``rws_subscription`` on 2.0) as XHTML.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

__all__ = ["Dialect", "DIALECTS", "ROBID_VARS", "ROBID_TASK", "ROBID_MODULE", "PATH_MODULE",
           "PATH_PROC", "RAPID_STRING_MAX", "rapid_string_value", "rapid_string_text",
           "done_value", "size_value", "error_value", "check_path_module", "event_page",
           "value_event", "exec_event"]

# -- the robid RAPID module (README, "Driver abb_rws"): installed once in T_ROB1
ROBID_TASK, ROBID_MODULE = "T_ROB1", "robid"
ROBID_VARS = ("robid_exp", "robid_nonce", "robid_size", "robid_done", "robid_params",
              "robid_params_ack")
#: each experiment's module is loaded (replace) as robid_path; robid's main calls robid_move
PATH_MODULE, PATH_PROC = "robid_path", "robid_move"
#: a RAPID string holds at most 80 characters (RAPID reference, data type string)
RAPID_STRING_MAX = 80


@dataclass(frozen=True)
class Dialect:
    """One RWS version: routes as ``(method, path template, action)`` → handler name (the
    action is the ``?action=`` of 1.0, None where 2.0 puts it in the path), encodings, the
    subscription resources and the JSON envelope."""

    version: int
    routes: tuple[tuple[str, str, str | None, str], ...]
    accept: str | None          # an Accept the answers demand (2.0), None: any
    form: str | None            # the Content-Type of a POST body (2.0), None: any form
    uploads: tuple[str, ...]    # Content-Types of a file-service upload (2.0), () any
    json_query: bool            # ?json=1 asks for JSON (1.0)
    home: str                   # the HOME environment variable in a file-service URI
    subprotocol: str
    symbol_resource: str        # subscription resource of a RAPID variable's value
    exec_resource: str = "/rw/rapid/execution;ctrlexecstate"

    def envelope(self, items: list[dict[str, Any]]) -> dict[str, Any]:
        """A JSON answer holding ``items`` (1.0: ``_embedded._state``, 2.0: ``state``)."""
        return {"_embedded": {"_state": items}} if self.version == 1 else {"state": items}

    def error(self, code: int, msg: str) -> dict[str, Any]:
        doc = {"status": {"code": code, "msg": msg}}
        return {"_embedded": doc} if self.version == 1 else doc

    def variable_resource(self, var: str) -> str:
        return self.symbol_resource.format(task=ROBID_TASK, module=ROBID_MODULE, var=var)


_EXEC_ROUTES_1 = (
    ("GET", "/rw/rapid/execution", None, "get_execution"),
    ("POST", "/rw/rapid/execution", "start", "start"),        # regain, execmode, cycle, …
    ("POST", "/rw/rapid/execution", "stop", "stop"),          # stopmode
    ("POST", "/rw/rapid/execution", "resetpp", "resetpp"),
)
_EXEC_ROUTES_2 = (
    ("GET", "/rw/rapid/execution", None, "get_execution"),
    ("POST", "/rw/rapid/execution/start", None, "start"),
    ("POST", "/rw/rapid/execution/stop", None, "stop"),
    ("POST", "/rw/rapid/execution/resetpp", None, "resetpp"),
)

DIALECTS: dict[int, Dialect] = {
    1: Dialect(
        1,
        (("POST", "/rw/mastership", "request", "mastership_request"),      # all domains
         ("POST", "/rw/mastership", "release", "mastership_release"),
         ("POST", "/rw/mastership/rapid", "request", "mastership_request"),  # one domain
         ("POST", "/rw/mastership/rapid", "release", "mastership_release"),
         ("POST", "/rw/rapid/tasks/{task}", "loadmod", "loadmod"),          # modulepath, replace
         ("GET", "/rw/rapid/symbol/data/RAPID/{task}/{module}/{var}", None, "get_symbol"),
         ("POST", "/rw/rapid/symbol/data/RAPID/{task}/{module}/{var}", "set", "set_symbol"),
         *_EXEC_ROUTES_1),
        accept=None, form=None, uploads=(), json_query=True, home="$home",
        subprotocol="robapi2_subscription",
        symbol_resource="/rw/rapid/symbol/data/RAPID/{task}/{module}/{var};value"),
    2: Dialect(
        2,
        (("POST", "/rw/mastership/edit/request", None, "mastership_request"),
         ("POST", "/rw/mastership/edit/release", None, "mastership_release"),
         ("POST", "/rw/rapid/tasks/{task}/loadmod", None, "loadmod"),
         ("GET", "/rw/rapid/symbol/RAPID/{task}/{module}/{var}/data", None, "get_symbol"),
         ("POST", "/rw/rapid/symbol/RAPID/{task}/{module}/{var}/data", None, "set_symbol"),
         *_EXEC_ROUTES_2),
        accept="application/hal+json;v=2.0", form="application/x-www-form-urlencoded;v=2.0",
        uploads=("application/octet-stream;v=2.0", "text/plain;v=2.0"), json_query=False,
        home="$HOME", subprotocol="rws_subscription",
        symbol_resource="/rw/rapid/symbol/RAPID/{task}/{module}/{var}/data;value"),
}


def rapid_string_value(text: str) -> str:
    """A RAPID string as RWS shows a value: in double quotes, a quote inside doubled."""
    return '"' + text.replace('"', '""') + '"'


def rapid_string_text(value: str) -> str | None:
    """The text of a RAPID string value (``"…"``, quotes inside doubled); None when ``value``
    is not a string literal."""
    v = value.strip()
    if len(v) < 2 or v[0] != '"' or v[-1] != '"' or re.search(r'(?<!")"(?!")', v[1:-1]
                                                                ) is not None:
        return None
    return v[1:-1].replace('""', '"')


def done_value(nonce: str, sha256: str) -> str:
    """``robid_done`` once the log is closed (README sketch): ``<nonce> <sha256>``, 73
    characters with the daemon's 8-character nonces."""
    return f"{nonce} {sha256}"


def size_value(nonce: str, size: int) -> str:
    """``robid_size``, written before ``robid_done``: ``<nonce> <bytes>``."""
    return f"{nonce} {size}"


def error_value(nonce: str, text: str) -> str:
    """``robid_done`` of a failed run: ``ERR <nonce> <text>``, within a RAPID string."""
    return f"ERR {nonce} {' '.join(text.split())}"[:RAPID_STRING_MAX]


_JOINTTARGET = re.compile(r"\[\[([^\[\]]*)\],\[([^\[\]]*)\]\]")
_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


def check_path_module(text: str) -> str | None:
    """Why ``text`` is not a loadable experiment module (None when it is): ``MODULE
    robid_path`` … ``ENDMODULE`` with ``PROC robid_move()`` and every ``jointtarget`` array's
    elements ``[[6 robot axes],[6 external axes]]`` (RAPID reference, data type jointtarget),
    as many as declared."""
    lines = [ln.strip() for ln in text.strip().splitlines()]
    if not lines or not re.fullmatch(rf"MODULE {PATH_MODULE}(\(.*\))?", lines[0]):
        return f"first line is not MODULE {PATH_MODULE}"
    if lines[-1] != "ENDMODULE":
        return "no ENDMODULE at the end"
    if not any(re.fullmatch(rf"PROC {PATH_PROC}\(\)", ln) for ln in lines):
        return f"no PROC {PATH_PROC}()"
    if lines.count("ENDPROC") < 1:
        return "no ENDPROC"
    for m in re.finditer(r"jointtarget\s+(\w+)\{(\d+)\}\s*:=\s*\[(.*?)\];", text, re.S):
        targets = _JOINTTARGET.findall(m.group(3))
        if len(targets) != int(m.group(2)):
            return f"{m.group(1)}: {len(targets)} joint targets, {m.group(2)} declared"
        for rob, ext in targets:
            nums = rob.split(",") + ext.split(",")
            if len(nums) != 12 or not all(_NUM.match(x.strip()) for x in nums):
                return f"{m.group(1)}: a jointtarget is not [[6 numbers],[6 numbers]]"
    return None


def _xml(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def event_page(sid: str, items: str) -> str:
    """One websocket event message: an XHTML page whose ``<ul>`` holds the changes."""
    return ('<?xml version="1.0" encoding="utf-8"?><html xmlns="http://www.w3.org/1999/xhtml">'
            '<head><title>Event</title></head><body><div class="state">'
            f'<a href="subscription/{sid}" rel="group"></a><ul>{items}</ul></div></body></html>')


def value_event(resource: str, var: str, value: str) -> str:
    """A RAPID variable changed: ``rap-value-ev`` naming the resource, and the new value."""
    return (f'<li class="rap-value-ev" title="value"><a href="{resource}" rel="self"/></li>'
            f'<li class="rap-data" title="RAPID/{ROBID_TASK}/{ROBID_MODULE}/{var}">'
            f'<span class="value">{_xml(value)}</span></li>')


def exec_event(resource: str, state: str) -> str:
    """The execution state changed (``running`` / ``stopped``)."""
    return (f'<li class="rap-ctrlexecstate-ev" title="ctrlexecstate"><a href="{resource}" '
            f'rel="self"/><span class="ctrlexecstate">{state}</span></li>')
