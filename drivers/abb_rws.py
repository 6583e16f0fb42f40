"""The link over ABB Robot Web Services (RobComm's successor): RWS 1.0 on IRC5 (Digest auth),
RWS 2.0 on OmniCore (Basic auth over HTTPS), one driver, the differences in ``rws_api.API``.

put: the RAPID module and the neutral trajectory through the file service, then ``loadmod``
under RAPID mastership; give: ``robid_exp``/``robid_nonce`` and start; take: a websocket
subscription on ``robid_done`` and the execution state (no polling), re-made after a restart
or a silent socket and followed each time by asking the state; fetch: the log through the file
service. aiohttp: a maintained asyncio HTTP client with Digest auth (``DigestAuthMiddleware``),
a websocket client, and a server for the fake (one library, no second event loop or thread).

A controller is trusted with nothing: every answer is read up to a cap (``max_answer_bytes``,
the log up to ``max_log_bytes``) and parsed as the manual says or refused in one line; no
redirect is ever followed (HTTP or websocket: it would carry the session elsewhere); the
credentials come from an owner-only file or the daemon's environment, never from the URL.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import hashlib
import ipaddress
import json
import logging
import os
import re
import ssl
from collections.abc import AsyncIterator, Mapping
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import aiohttp
from yarl import URL

from robid_link.drivers.rapid import MAX_AXES, render_rapid
from robid_link.drivers.rws_api import (
    API,
    HOME,
    credentials,
    log_file,
    parse_done,
    parse_rapid_string,
    parse_size,
    program_file,
    rapid_string,
    rws_module,
)
from robid_link.exceptions import ConfigError, DriverError
from robid_link.jobs import MotionProgram, RobotInfo
from robid_link.link.driver import CAP_RAPID, CAP_UPLOAD, Done, Driver
from robid_link.link.options import Choice, File, Flag, Integer, Number, Options, Text, Url
from robid_link.link.retry import Backoff

__all__ = ["AbbRwsDriver"]

log = logging.getLogger("robid.driver.abb_rws")

_IDENT = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}$")
_START = {"regain": "continue", "execmode": "continue", "cycle": "once", "condition": "none",
          "stopatbp": "disabled", "alltaskbytsp": "false"}
#: a file upload's Content-Type: RWS 2.0 refuses any but its versioned types (HTTP 415)
_UPLOAD_TYPE = {1: None, 2: "application/octet-stream;v=2.0"}


class _Lost(Exception):
    """The subscription's websocket closed or went silent: subscribe again, then ask."""


class _Unavailable(DriverError):
    """The controller did not answer (503, refused connection) within the bounded retries."""


_REDIRECTS = frozenset({301, 302, 303, 307, 308})


async def _no_redirects(req: Any, handler: Any) -> Any:
    """A client middleware (it sees every hop, the websocket's handshake too): a redirect is
    refused, never followed — the session cookie and the Authorization header stay here."""
    resp = await handler(req)
    if resp.status in _REDIRECTS:
        resp.release()
        raise DriverError(f"abb_rws: {req.method} {req.url.path}: HTTP {resp.status} redirect "
                          "refused (a redirect is never followed: it would carry the session "
                          "elsewhere)")
    return resp


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class AbbRwsDriver(Driver):
    """Daemon side of the RWS link. Options: ``url`` (http(s)://controller[:port]),
    ``version`` (1: IRC5, 2: OmniCore), ``credentials_file`` (owner-only), ``task``,
    ``module`` (the installed robid RAPID module), ``ca_file``, ``verify_tls``,
    ``insecure_skip_verify``, ``ping_interval_s`` (the controller's websocket ping period; two
    missed pings = a lost link), ``request_timeout_s``, ``retries``, ``backoff_s``,
    ``max_answer_bytes`` (the largest answer or event but the log). Without
    ``credentials_file`` the user and password come from ``ROBID_RWS_USER`` and
    ``ROBID_RWS_PASSWORD``."""

    name = "abb_rws"
    capabilities = frozenset({CAP_RAPID, CAP_UPLOAD})
    options = Options(
        version=Choice(1, 2, expect="1 (RWS 1.0, IRC5) or 2 (RWS 2.0, OmniCore)"),
        url=Url(hint="http(s)://controller[:port]"),
        credentials_file=File(None, private=True),
        task=Text("T_ROB1", pattern=_IDENT.pattern, expect="a RAPID name"),
        module=Text("robid", pattern=_IDENT.pattern, expect="a RAPID name"),
        ca_file=File(None, exists=True), verify_tls=Flag(True),
        insecure_skip_verify=Flag(False), ping_interval_s=Number(30.0, above=0),
        request_timeout_s=Number(10.0, above=0), retries=Integer(5, low=0),
        backoff_s=Number(0.5, above=0),
        max_answer_bytes=Integer(1 << 20, low=4096, high=1 << 30))

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        o = self.config
        self.api = API[o.version]
        self._url = self._check_url(o.url, o.version)
        self._user, self._password, self.credentials_file = credentials(o.credentials_file,
                                                                        os.environ)
        self._answer_cap, self._log_cap = o.max_answer_bytes, o.max_log_bytes
        self.task, self.module = o.task, o.module
        self._ssl = self._tls(o.ca_file, o.verify_tls, o.insecure_skip_verify)
        self._ping_s, self._request_s = o.ping_interval_s, o.request_timeout_s
        # a busy controller (HTTP 503, session limit) and a lost subscription are retried
        # with growing, jittered waits: at most 10 s and 5 s
        self._retry = Backoff(o.backoff_s, max(10.0, o.backoff_s))
        self._resubscribe = Backoff(o.backoff_s, max(5.0, o.backoff_s))
        self._retries = o.retries
        self._http: aiohttp.ClientSession | None = None

    @staticmethod
    def _check_url(url: str, version: int) -> URL:
        u = URL(url)  # checked by the Url option: a scheme, a host, no credentials, no path
        # (the option leaves no URL without a host; none would count as not loopback)
        if version == 2 and u.scheme == "http" and not _loopback(u.host or ""):
            raise ConfigError("driver.url: RWS 2.0 sends the password with every request "
                              "(Basic auth): use https://")
        return u.with_path("/")

    def _tls(self, ca_file: Path | None, verify: bool, insecure: bool
             ) -> ssl.SSLContext | bool:
        if not verify and not insecure:
            raise ConfigError("driver.verify_tls: false needs driver.insecure_skip_verify: "
                              "true as well (verification is only turned off explicitly)")
        if insecure:
            return False
        if self._url.scheme != "https":
            return True
        try:
            return ssl.create_default_context(cafile=ca_file)
        except (OSError, ssl.SSLError) as err:
            raise ConfigError(f"driver.ca_file: {ca_file}: not a PEM certificate ({err})"
                              ) from err

    def _check_robot(self, robot: RobotInfo) -> None:
        if robot.n > MAX_AXES:
            raise ConfigError(f"driver.name: RAPID joint targets hold at most {MAX_AXES} axes, "
                              f"robot {robot.name} has {robot.n}")

    # -- HTTP
    async def _open(self) -> None:
        jar = aiohttp.CookieJar(unsafe=True)  # controllers are addressed by IP
        conn = aiohttp.TCPConnector(ssl=self._ssl, limit=4)
        if self.api.version == 1:
            self._http = aiohttp.ClientSession(
                connector=conn, cookie_jar=jar,
                middlewares=(_no_redirects,
                             aiohttp.DigestAuthMiddleware(self._user, self._password)))
        else:
            # Basic on every request (no redirect is followed: it never reaches another
            # host); built by hand, aiohttp deprecates BasicAuth after 3.12
            token = base64.b64encode(f"{self._user}:{self._password}".encode()).decode()
            self._http = aiohttp.ClientSession(connector=conn, cookie_jar=jar,
                                               middlewares=(_no_redirects,),
                                               headers={"Authorization": f"Basic {token}"})
        try:
            await self._request("GET", "/", dict(self.api.query), what="login")
        except BaseException:
            await self._http.close()
            raise
        log.info("driver=abb_rws url=%s rws=%d.0 user=%s session open", self._url,
                 self.api.version, self._user)

    async def _close(self) -> None:
        http, self._http = self._http, None
        if http is None:
            return
        try:
            async with asyncio.timeout(min(self._request_s, 3.0)):
                async with http.get(self._url.with_path("/logout"), allow_redirects=False,
                                    params=dict(self.api.query)) as resp:
                    await self._read(resp, self._answer_cap, "logout")
        except (aiohttp.ClientError, OSError, TimeoutError, DriverError) as err:
            log.info("driver=abb_rws logout failed (%s); the controller drops the session "
                     "itself", type(err).__name__)
        finally:
            await http.close()

    async def _request(self, method: str, path: str, query: Mapping[str, str] | None = None,
                       *, form: Mapping[str, str] | list[tuple[str, str]] | None = None,
                       raw: bytes | None = None, what: str, ok: tuple[int, ...] = (200, 201,
                                                                                    204),
                       missing_ok: bool = False, retries: int | None = None,
                       cap: int | None = None, timeout_s: float | None = None
                       ) -> tuple[int, bytes, Any]:
        """One RWS call with bounded, jittered retries on 503 (session limit, start-up) and
        lost connections; 401, TLS failures, redirects and answers over ``cap`` bytes
        (``max_answer_bytes``) are refused at once, in one line. Each attempt has
        ``timeout_s`` (``request_timeout_s``)."""
        assert self._http is not None
        url = self._url.with_path(path, encoded=True)
        headers = self.api.headers(form is not None)
        if path.startswith("/fileservice"):
            upload = _UPLOAD_TYPE[self.api.version] if raw is not None else None
            headers = {"Content-Type": upload} if upload else {}
        data = urlencode(form).encode() if form is not None else raw
        last = ""
        retries = self._retries if retries is None else retries
        cap = self._answer_cap if cap is None else cap
        for attempt in range(retries + 1):
            try:
                async with asyncio.timeout(timeout_s or self._request_s):
                    async with self._http.request(method, url, params=query, data=data,
                                                  headers=headers,
                                                  allow_redirects=False) as resp:
                        status, rh = resp.status, resp.headers
                        body = await self._read(resp, cap, what)
            except aiohttp.ClientConnectorCertificateError as err:
                raise DriverError(f"{self.name}: {self._url}: TLS certificate verification "
                                  f"failed ({err.certificate_error}); give driver.ca_file, or "
                                  "set driver.insecure_skip_verify: true") from err
            except aiohttp.ClientSSLError as err:
                raise DriverError(f"{self.name}: {self._url}: TLS failed ({err})") from err
            except (aiohttp.ClientError, OSError, TimeoutError) as err:
                last = f"{type(err).__name__}: {err}".splitlines()[0][:160]
            else:
                if status in ok or (missing_ok and status == 404):
                    return status, body, rh
                if status == 401:
                    raise DriverError(f"{self.name}: {self._url}: login refused (HTTP 401): "
                                      f"check the user and password in {self.credentials_file}")
                if status != 503:
                    raise DriverError(f"{self.name}: {what}: HTTP {status}"
                                      f"{self._rws_message(body)}")
                last = "HTTP 503 (too many sessions, or the controller is starting)"
            if attempt < retries:
                delay = self._retry.delay(attempt + 1)
                log.warning("driver=abb_rws %s: %s; retry %d/%d in %.2f s", what, last,
                            attempt + 1, retries, delay)
                await asyncio.sleep(delay)
        raise _Unavailable(f"{self.name}: {what}: controller unavailable after "
                           f"{retries + 1} attempt{'s' if retries else ''} ({last})")

    async def _read(self, resp: aiohttp.ClientResponse, cap: int, what: str) -> bytes:
        """The body, refused as soon as it is over ``cap`` bytes (never held whole)."""
        limit = ("driver.max_answer_bytes" if cap == self._answer_cap else
                 "driver.max_log_bytes" if cap == self._log_cap else "the size 'done' announced")
        too_big = DriverError(f"{self.name}: {what}: answer over {cap} bytes refused "
                              f"({limit})")
        if resp.content_length is not None and resp.content_length > cap:
            raise too_big
        chunks, total = [], 0
        async for chunk in resp.content.iter_chunked(1 << 16):
            total += len(chunk)
            if total > cap:
                raise too_big
            chunks.append(chunk)
        return b"".join(chunks)

    def _rws_message(self, body: bytes) -> str:
        try:
            doc = json.loads(body)
        except ValueError:
            return ""
        status = (doc.get("_embedded", doc) if isinstance(doc, dict) else {}).get("status", {})
        msg = status.get("msg") if isinstance(status, dict) else None
        return f": {str(msg)[:160]}" if msg else ""

    async def _call(self, which: str, form: Mapping[str, str] | None = None, *,
                    what: str, **names: str) -> Any:
        """An action of the version table; a JSON answer parsed, else None."""
        path, query = self.api.path(which, task=self.task, module=self.module, **names)
        method = "GET" if form is None and which in ("symbol", "execution") else "POST"
        _, body, _ = await self._request(method, path, query, form=form if method == "POST"
                                         else None, what=what)
        if not body.strip():
            return None
        try:
            return json.loads(body)
        except ValueError as err:  # JSONDecodeError, UnicodeDecodeError
            raise DriverError(f"{self.name}: {what}: the answer is not JSON "
                              f"({body[:40]!r}…)") from err

    async def _get_var(self, var: str) -> str:
        doc = await self._call("symbol", what=f"read {var}", var=var)
        state = self.api.state(doc)
        if not state or "value" not in state[0]:
            raise DriverError(f"{self.name}: read {var}: no value in the answer")
        return parse_rapid_string(str(state[0]["value"]))

    async def _set_var(self, var: str, value: str) -> None:
        await self._call("symbol_set", {"value": rapid_string(value)}, what=f"write {var}",
                         var=var)

    async def _exec_state(self) -> str:
        state = self.api.state(await self._call("execution", what="execution state"))
        if not state or "ctrlexecstate" not in state[0]:
            raise DriverError(f"{self.name}: execution state: no ctrlexecstate in the answer")
        value = state[0]["ctrlexecstate"]
        if value not in ("running", "stopped"):
            raise DriverError(f"{self.name}: execution state: ctrlexecstate {str(value)[:40]!r}"
                              ", expected running or stopped")
        return str(value)

    @contextlib.asynccontextmanager
    async def _mastership(self) -> AsyncIterator[None]:
        await self._call("mastership_request", {}, what="request RAPID mastership")
        try:
            yield
        finally:
            await self._call("mastership_release", {}, what="release RAPID mastership")

    async def _put_file(self, remote: str, data: bytes) -> None:
        await self._request("PUT", self._file_uri(remote), raw=data, what=f"upload {remote}")

    def _file_uri(self, remote: str) -> str:
        """The file service's URI of a controller path; RWS 1.0 names environment variables
        in small case there (``$home``, ABB's RWS manual, "File Service")."""
        if self.api.version == 1 and remote.startswith("$HOME/"):
            remote = "$home/" + remote[len("$HOME/"):]
        return f"/fileservice/{remote}"

    # -- the cycle
    async def _put_program(self, program: MotionProgram) -> None:
        module = rws_module(render_rapid(program))
        exp = program.exp_id
        for suffix, data in (("traj.csv", program.files["traj.csv"]),
                             ("traj.yaml", program.files["traj.yaml"]), ("mod", module)):
            await self._put_file(program_file(exp, suffix), data)
        if await self._exec_state() == "running":
            if await self._get_var("robid_exp") == exp:  # given before a daemon restart
                log.info("driver=abb_rws exp=%s already running; module left as loaded", exp)
                return
            raise DriverError(f"{self.name}: RAPID execution is running another program; "
                              f"refusing to load experiment {exp}")
        async with self._mastership():
            await self._call("loadmod", {"modulepath": program_file(exp, "mod"),
                                         "replace": "true"}, what=f"load module of {exp}")

    async def _give_ready(self, exp_id: str, nonce: str) -> None:
        if (await self._get_var("robid_nonce") == nonce
                and await self._get_var("robid_exp") == exp_id):
            return  # given before a restart: giving again must not start it twice
        if await self._exec_state() == "running":
            raise DriverError(f"{self.name}: RAPID execution is running; refusing to start "
                              f"experiment {exp_id}")
        async with self._mastership():
            await self._set_var("robid_done", "")
            await self._set_var("robid_size", "")
            await self._set_var("robid_exp", exp_id)
            await self._set_var("robid_nonce", nonce)  # last: the mark that it was given
            await self._call("exec_resetpp", {}, what="reset the program pointer")
        await self._call("exec_start", _START, what=f"start experiment {exp_id}")
        log.info("driver=abb_rws exp=%s nonce=%s started", exp_id, nonce)

    async def _wait_done(self, exp_id: str, nonce: str) -> Done:
        lost = 0
        while True:
            try:
                async with self._subscription() as ws:
                    while True:  # ask after subscribing and after every event
                        done = await self._ask(exp_id, nonce)
                        if done is not None:
                            return done
                        await self._next_event(ws)
            except (_Lost, _Unavailable) as err:
                lost += 1
                delay = self._resubscribe.delay(lost)
                log.warning("driver=abb_rws exp=%s subscription lost (%s); subscribing again in "
                            "%.2f s and asking the state", exp_id, err, delay)
                await asyncio.sleep(delay)

    async def _ask(self, exp_id: str, nonce: str) -> Done | None:
        """The state as the controller has it now: ours done, ours failed, or still running."""
        done = await self._look(exp_id, nonce)
        if done is not None or await self._exec_state() != "stopped":
            return done
        done = await self._look(exp_id, nonce)  # a program writes robid_done before it ends
        if done is None and await self._get_var("robid_nonce") == nonce:
            raise DriverError(f"{self.name}: RAPID execution stopped during experiment {exp_id} "
                              "without a 'done' (execution error: see the controller's event "
                              "log)")
        return done

    async def _look(self, exp_id: str, nonce: str) -> Done | None:
        parsed = parse_done(await self._get_var("robid_done"))
        if parsed is None:
            return None
        kind, got, text = parsed
        if got != nonce:
            log.warning("driver=abb_rws exp=%s stale answer for nonce %s (waiting for %s; "
                        "ignored)", exp_id, got[:16], nonce)
            return None
        if kind == "error":
            raise DriverError(f"controller reports experiment {exp_id} failed: {text}")
        size = parse_size(await self._get_var("robid_size"), nonce)
        return Done(exp_id, nonce, text, size)

    @contextlib.asynccontextmanager
    async def _subscription(self) -> AsyncIterator[aiohttp.ClientWebSocketResponse]:
        assert self._http is not None
        a = self.api
        done_res = a.symbol_event.format(task=self.task, module=self.module, var="robid_done")
        form = [("resources", "1"), ("1", done_res), ("1-p", "1"),
                ("resources", "2"), ("2", a.exec_event), ("2-p", "1")]
        _, _, headers = await self._request("POST", "/subscription", dict(a.query), form=form,
                                            what="subscribe", ok=(201,))
        loc = URL(headers.get("Location", ""))
        if not loc.path.startswith("/poll/"):
            raise DriverError(f"{self.name}: subscribe: no websocket /poll/ location in the "
                              "answer")
        # the socket goes to the controller we logged in to, whatever host Location names
        ws_url = self._url.with_scheme("wss" if self._url.scheme == "https" else "ws"
                                       ).with_path(loc.path)
        try:
            async with asyncio.timeout(self._request_s):
                ws = await self._http.ws_connect(ws_url, protocols=(a.subprotocol,),
                                                 autoping=False,
                                                 max_msg_size=self._answer_cap)
        except (aiohttp.ClientError, OSError, TimeoutError) as err:
            raise _Lost(f"websocket: {type(err).__name__}") from err
        try:
            yield ws
        finally:
            await ws.close()
            with contextlib.suppress(DriverError, aiohttp.ClientError, OSError):
                await self._request("DELETE", f"/subscription/{loc.name}", what="unsubscribe",
                                    missing_ok=True, retries=0)

    async def _next_event(self, ws: aiohttp.ClientWebSocketResponse) -> str:
        """The next event's text; the controller's pings answered on the way. Two ping periods
        without a frame, or a closed socket, is a lost link."""
        while True:
            try:
                async with asyncio.timeout(2 * self._ping_s):
                    msg = await ws.receive()
            except TimeoutError:
                raise _Lost(f"no ping or event for {2 * self._ping_s:g} s") from None
            if msg.type == aiohttp.WSMsgType.PING:
                await ws.pong(msg.data)
            elif msg.type == aiohttp.WSMsgType.TEXT:
                return str(msg.data)
            elif msg.type != aiohttp.WSMsgType.PONG:
                raise _Lost(f"websocket {msg.type.name.lower()}")

    async def _fetch_logs(self, done: Done) -> bytes:
        remote = log_file(done.exp_id, done.nonce)
        status, body, _ = await self._request("GET", self._file_uri(remote),
                                              what=f"download {remote}", missing_ok=True,
                                              cap=min(self._log_cap, done.size)
                                              if done.size is not None else self._log_cap,
                                              timeout_s=self.config.transfer_timeout_s)
        if status == 404:
            raise DriverError(f"{self.name}: {remote}: log missing although 'done' was given")
        return body

    async def _withdraw(self, exp_id: str, nonce: str) -> None:
        """Stop RAPID execution if it may run this attempt: unless the controller shows, in
        answers that parse, another nonce or a stopped execution, the stop goes out."""
        try:
            ours = (await self._get_var("robid_nonce") == nonce
                    and await self._exec_state() == "running")
        except DriverError as err:
            log.warning("driver=abb_rws exp=%s state unreadable (%s): stopping anyway",
                        exp_id, err)
            ours = True
        if ours:
            log.warning("driver=abb_rws exp=%s nonce=%s given up: stopping RAPID execution",
                        exp_id, nonce)
            await self._call("exec_stop", {"stopmode": "stop"}, what=f"stop {exp_id}")

    async def _upload_parameters(self, doc: Mapping[str, Any], body: bytes) -> None:
        """The set's file through the file service, its path into ``robid_params``; the
        robid module loads it and answers ``robid_params_ack`` = ``<sha16> OK`` (or
        ``<sha16> ERR <reason>``). A rare operation: the answer is read every 0.2 s under
        the caller's timeout."""
        # robid_params holds the path: a RAPID string holds at most 80 characters, and
        # "$HOME/robid/params/" + ".<tag>.json" leave 39 for the robot's name
        robot = re.sub(r"[^A-Za-z0-9_\-]", "_", str(doc.get("robot", "robot")))[:39]
        tag = hashlib.sha256(body).hexdigest()[:16]
        remote = f"{HOME}/params/{robot}.{tag}.json"
        await self._put_file(remote, body)
        async with self._mastership():
            await self._set_var("robid_params_ack", "")
            await self._set_var("robid_params", remote)
        while True:
            ack = await self._get_var("robid_params_ack")
            if ack.startswith(f"{tag} OK"):
                return
            if ack.startswith(f"{tag} ERR"):
                raise DriverError(f"{self.name}: the controller refused parameter set {tag}: "
                                  f"{ack.split(' ', 2)[-1]}")
            await asyncio.sleep(0.2)

    async def _withdraw_parameters(self, doc: Mapping[str, Any], body: bytes) -> None:
        async with self._mastership():
            await self._set_var("robid_params", "")
