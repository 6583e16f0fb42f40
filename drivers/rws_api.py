"""ABB Robot Web Services as robid uses them: the resource paths and encodings of RWS 1.0
(IRC5, RobotWare 6) and 2.0 (OmniCore, RobotWare 7) in one table, and the robid RAPID names.

Shared by the driver (``abb_rws.py``) and the fake controller (``fakes/rws/peer.py``), like the
file-share names: the peer serves exactly what this table names, nothing more.
"""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import yaml

from robid_link.exceptions import ConfigError, DriverError

__all__ = ["RwsApi", "API", "VARS", "HOME", "PATH_MODULE", "PATH_PROC", "RAPID_STRING_MAX",
           "done_value", "size_value", "error_value", "parse_done", "parse_size",
           "rapid_string", "parse_rapid_string", "read_credentials", "credentials",
           "CREDENTIAL_ENV", "log_file", "program_file", "rws_module"]

#: the fixed RAPID module the cell installs once, its variables (strings), and the name the
#: daemon gives every experiment's motion module (loaded with ``replace``: one at a time).
#: ``robid_done`` holds "<nonce> <sha256>" (73 characters) and ``robid_size`` "<nonce> <bytes>",
#: written before it: "<nonce> <sha256> <size>" in one string passed RAPID's 80 characters for
#: logs of 1 MB or more
VARS = ("robid_exp", "robid_nonce", "robid_size", "robid_done", "robid_params",
        "robid_params_ack")
#: a RAPID string holds at most 80 characters (RAPID reference, data type string)
RAPID_STRING_MAX = 80
#: where the daemon's environment may give the RWS user and password instead of a file
CREDENTIAL_ENV = ("ROBID_RWS_USER", "ROBID_RWS_PASSWORD")
PATH_MODULE = "robid_path"
PATH_PROC = "robid_move"
#: the folder on the controller's disk (file service) for programs, logs and parameters
HOME = "$HOME/robid"
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


@dataclass(frozen=True)
class RwsApi:
    """One RWS version: how a request is encoded and where each action lives. Paths are
    ``(path, query)``; ``{task}``, ``{module}`` and ``{var}`` are filled in by ``path``."""

    version: int
    accept: str
    content_type: str
    subprotocol: str
    query: tuple[tuple[str, str], ...]
    mastership_request: tuple[str, str | None]
    mastership_release: tuple[str, str | None]
    loadmod: tuple[str, str | None]
    symbol: tuple[str, str | None]          # GET the value
    symbol_set: tuple[str, str | None]      # POST value=…
    symbol_event: str                       # subscription resource of a value
    execution: tuple[str, str | None]
    exec_start: tuple[str, str | None]
    exec_stop: tuple[str, str | None]
    exec_resetpp: tuple[str, str | None]
    exec_event: str
    state_key: tuple[str, ...]              # where the state list sits in a JSON answer

    def path(self, which: str, **names: str) -> tuple[str, dict[str, str]]:
        """The path and query of action ``which`` (``?action=`` on 1.0, ``?json=1`` too)."""
        path, action = getattr(self, which)
        query = dict(self.query)
        if action:
            query["action"] = action
        return path.format(**names), query

    def headers(self, body: bool = False) -> dict[str, str]:
        h = {"Accept": self.accept}
        if body:
            h["Content-Type"] = self.content_type
        return h

    def state(self, doc: object) -> list[dict[str, object]]:
        """The ``_state``/``state`` list of a JSON answer (an empty list when absent)."""
        for key in self.state_key:
            doc = doc.get(key) if isinstance(doc, dict) else None
        return [x for x in doc if isinstance(x, dict)] if isinstance(doc, list) else []


_SYM1 = "/rw/rapid/symbol/data/RAPID/{task}/{module}/{var}"
_SYM2 = "/rw/rapid/symbol/RAPID/{task}/{module}/{var}/data"

API: dict[int, RwsApi] = {
    1: RwsApi(1, "application/json", "application/x-www-form-urlencoded",
              "robapi2_subscription", (("json", "1"),),
              ("/rw/mastership", "request"), ("/rw/mastership", "release"),
              ("/rw/rapid/tasks/{task}", "loadmod"),
              (_SYM1, None), (_SYM1, "set"), _SYM1 + ";value",
              ("/rw/rapid/execution", None), ("/rw/rapid/execution", "start"),
              ("/rw/rapid/execution", "stop"), ("/rw/rapid/execution", "resetpp"),
              "/rw/rapid/execution;ctrlexecstate", ("_embedded", "_state")),
    2: RwsApi(2, "application/hal+json;v=2.0", "application/x-www-form-urlencoded;v=2.0",
              "rws_subscription", (),
              ("/rw/mastership/edit/request", None), ("/rw/mastership/edit/release", None),
              ("/rw/rapid/tasks/{task}/loadmod", None),
              (_SYM2, None), (_SYM2, None), _SYM2 + ";value",
              ("/rw/rapid/execution", None), ("/rw/rapid/execution/start", None),
              ("/rw/rapid/execution/stop", None), ("/rw/rapid/execution/resetpp", None),
              "/rw/rapid/execution;ctrlexecstate", ("state",)),
}


def rapid_string(text: str) -> str:
    """A RAPID string literal as RWS takes it in ``value=`` (quotes doubled inside)."""
    return '"' + text.replace('"', '""') + '"'


def parse_rapid_string(value: str) -> str:
    v = value.strip()
    if len(v) >= 2 and v[0] == v[-1] == '"':
        return v[1:-1].replace('""', '"')
    return v


def done_value(nonce: str, sha256: str) -> str:
    """What the robid RAPID module writes into ``robid_done`` when the log is on disk (its
    size went into ``robid_size`` just before)."""
    return f"{nonce} {sha256}"


def size_value(nonce: str, size: int) -> str:
    """What the robid RAPID module writes into ``robid_size`` before ``robid_done``."""
    return f"{nonce} {size}"


def error_value(nonce: str, text: str) -> str:
    return f"ERR {nonce} {text}"[:RAPID_STRING_MAX]


def parse_done(value: str) -> tuple[str, str, str] | None:
    """``robid_done`` → ``("done", nonce, sha256)`` or ``("error", nonce, text)``; None while
    empty; DriverError when malformed."""
    tokens = value.split()
    if not tokens:
        return None
    if tokens[0] == "ERR" and len(tokens) >= 2:
        return "error", tokens[1], " ".join(tokens[2:]) or "no reason given"
    if len(tokens) == 2 and _HEX64.match(tokens[1].lower()):
        return "done", tokens[0], tokens[1].lower()
    raise DriverError(f"robid_done {value[:80]!r}: expected '<nonce> <sha256>' or "
                      "'ERR <nonce> <text>'")


def parse_size(value: str, nonce: str) -> int:
    """The log size in ``robid_size`` (``"<nonce> <bytes>"``) for ``nonce``; DriverError when
    it is malformed or names another nonce (written after 'done', or not at all)."""
    tokens = value.split()
    if len(tokens) != 2 or not tokens[1].isdigit() or len(tokens[1]) > 12:
        raise DriverError(f"robid_size {value[:80]!r}: expected '<nonce> <bytes>'")
    if tokens[0] != nonce:
        raise DriverError(f"robid_size names nonce {tokens[0][:16]!r}, robid_done {nonce!r}: "
                          "the controller must write the size before 'done'")
    return int(tokens[1])


def log_file(exp_id: str, nonce: str) -> str:
    """The log the robid RAPID module writes for one experiment and nonce."""
    return f"{HOME}/{exp_id}.{nonce}.log.csv"


def program_file(exp_id: str, suffix: str) -> str:
    return f"{HOME}/{exp_id}.{suffix}"


def rws_module(rapid: bytes) -> bytes:
    """``render_rapid``'s module under the fixed name ``robid_path`` with its ``main`` as
    ``robid_move``: the robid module's ``main`` calls it by late binding, and loading the next
    experiment's module with ``replace`` takes this one's place (no unload bookkeeping)."""
    text = rapid.decode()
    text, n1 = re.subn(r"^MODULE \w+", f"MODULE {PATH_MODULE}", text, count=1, flags=re.M)
    text, n2 = re.subn(r"^(\s*)PROC main\(\)", rf"\1PROC {PATH_PROC}()", text, count=1,
                       flags=re.M)
    if n1 != 1 or n2 != 1:
        raise DriverError("RAPID module: no MODULE line or PROC main() to rename")
    return text.encode()


def credentials(path: str | os.PathLike[str] | None, env: Mapping[str, str],
                key: str = "driver.credentials_file") -> tuple[str, str, str]:
    """``(user, password, where)``: from the owner-only file ``path`` (``read_credentials``)
    or, without one, from the environment (``ROBID_RWS_USER``, ``ROBID_RWS_PASSWORD``);
    ``where`` names the source in messages (never the password)."""
    if path is not None:
        return (*read_credentials(path, key), str(path))
    user, password = (env.get(name, "") for name in CREDENTIAL_ENV)
    if not user or not password:
        raise ConfigError(f"{key}: missing (a file with the RWS user and password, readable "
                          f"only by the daemon's user; or {CREDENTIAL_ENV[0]} and "
                          f"{CREDENTIAL_ENV[1]} in the daemon's environment)")
    return user, password, f"{CREDENTIAL_ENV[0]}/{CREDENTIAL_ENV[1]}"


def read_credentials(path: str | os.PathLike[str], key: str = "driver.credentials_file"
                     ) -> tuple[str, str]:
    """``(user, password)`` from a file only its owner may read: a YAML mapping with ``user``
    and ``password``, or one ``user:password`` line. The password is never put in a message."""
    p = Path(path)
    try:
        st = p.stat()
        text = p.read_text()
    except OSError as err:
        raise ConfigError(f"{key}: {p}: cannot read ({err.strerror})") from err
    if st.st_mode & 0o077:
        raise ConfigError(f"{key}: {p} is readable by others (mode "
                          f"{stat.S_IMODE(st.st_mode):04o}); chmod 600 {p}")
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        raise ConfigError(f"{key}: {p} belongs to uid {st.st_uid}, not to the daemon's user "
                          f"(uid {os.getuid()})")
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError:
        doc = None
    if isinstance(doc, dict) and {"user", "password"} <= set(doc):
        user, password = doc["user"], doc["password"]
    else:
        user, sep, password = text.strip().splitlines()[0].partition(":") if text.strip() \
            else ("", "", "")
        if not sep:
            raise ConfigError(f"{key}: {p}: expected 'user: …' and 'password: …' or one "
                              "'user:password' line")
    if not isinstance(user, str) or not isinstance(password, str) or not user:
        raise ConfigError(f"{key}: {p}: user and password must be non-empty strings")
    return user, password
