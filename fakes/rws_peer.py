"""The controller side of the RWS link: an RWS 1.0 or 2.0 look-alike (aiohttp server and
websocket subscriptions on 127.0.0.1, a random port) serving exactly the calls of
``drivers/rws_api.py``, running each started program on the fake controller's plant.

Faults beyond the core's: ``restart`` (the controller restarts mid-program: sockets, sessions
and subscriptions gone, 503 for a moment, the program finishes meanwhile), ``silent_ws`` (the
socket stays open but carries neither pings nor events; the program ends once the daemon
subscribed again), ``exec_error`` (execution stops with
no 'done'), ``session_limit`` (503 for the first ``fault_count`` logins), ``bad_credentials``
(the daemon gets a wrong password). The server logs no secret: no password, no cookie.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import hashlib
import hmac
import itertools
import logging
import os
import re
import secrets
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from robid_link.atomic import atomic_write
from robid_link.drivers.rapid import parse_rapid
from robid_link.drivers.rws_api import (
    API,
    PATH_MODULE,
    VARS,
    done_value,
    error_value,
    log_file,
    parse_rapid_string,
)
from robid_link.exceptions import RobidError
from robid_link.fakes.controller import ControllerCore, Peer

__all__ = ["RwsPeer"]

log = logging.getLogger("robid.fake_controller.rws")

REALM = "validusers@robapi.abb"
_SESSION = web.RequestKey("session", str)
_DIGEST_FIELD = re.compile(r'(\w+)=(?:"([^"]*)"|([^,\s]*))')


def _state(version: int, items: list[dict[str, Any]]) -> dict[str, Any]:
    return {"_embedded": {"_state": items}} if version == 1 else {"state": items}


def _error(version: int, status: int, msg: str) -> web.Response:
    doc = {"status": {"code": -1073445879, "msg": msg}}
    return web.json_response({"_embedded": doc} if version == 1 else doc, status=status)


class RwsPeer(Peer):
    """Serve RWS ``version`` (1 or 2) from a thread with its own event loop; TLS (a
    self-signed certificate made with the ``openssl`` tool) by default on 2.0. Options:
    ``version``, ``tls`` (auto | true | false), ``ping_interval_s``, ``restart_s``."""

    driver = "abb_rws"
    faults = ("restart", "silent_ws", "exec_error", "session_limit", "bad_credentials")
    #: the contract suite runs once per RWS version (2.0: HTTPS, Basic auth, hal+json)
    contract_variants = ({"version": 1}, {"version": 2})

    def __init__(self, core: ControllerCore, workdir: Path, *, version: int = 1,
                 tls: str | bool = "auto", ping_interval_s: float = 30.0,
                 restart_s: float = 0.5, port: int = 0) -> None:
        super().__init__(core, workdir)
        if version not in (1, 2):
            raise ValueError(f"version: expected 1 or 2, got {version!r}")
        self.version, self.api = version, API[version]
        self.ping_s, self.restart_s, self.port = float(ping_interval_s), restart_s, port
        self.home = self.workdir / "HOME"
        (self.home / "robid").mkdir(parents=True, exist_ok=True)
        if tls == "auto":
            tls = version == 2 and shutil.which("openssl") is not None
        self.tls = bool(tls)
        self.user, self._password = "robid", secrets.token_urlsafe(12)
        self.credentials = self.workdir / "rws-credentials"
        wrong = core.fault == "bad_credentials"
        given = ("wrong-" if wrong else "") + self._password
        self.credentials.unlink(missing_ok=True)
        fd = os.open(self.credentials, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as fh:  # created owner-only: never readable by others
            fh.write(f"{self.user}:{given}\n")
        self.auth_attempts = self.logins = 0
        self.issued: list[str] = []  # session cookies handed out (tests look for leaks)
        self._busy = core.faults_left if core.fault == "session_limit" else 0
        self._sessions: set[str] = set()
        self._nonces: set[str] = set()
        self._master: str | None = None
        self.vars = dict.fromkeys(VARS, "")
        self.exec_state = "stopped"
        self._loaded = ""
        self._subs: dict[str, dict[str, Any]] = {}
        self._ids = itertools.count(1)
        self._down_until = 0.0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self._programs: list[threading.Thread] = []
        self._halt = threading.Event()
        self._lock = threading.Lock()

    # -- life cycle
    def driver_options(self) -> dict[str, Any]:
        opts: dict[str, Any] = {"name": "abb_rws", "version": self.version,
                                "url": f"{'https' if self.tls else 'http'}://127.0.0.1:"
                                       f"{self.port}",
                                "credentials_file": str(self.credentials),
                                "ping_interval_s": self.ping_s}
        if self.tls:
            opts["ca_file"] = str(self.workdir / "rws-cert.pem")
        return opts

    def start(self) -> None:
        if self._thread is not None:
            return
        ssl_ctx = self._tls_context() if self.tls else None
        self._loop = asyncio.new_event_loop()
        ready = threading.Event()
        failure: list[BaseException] = []
        self._thread = threading.Thread(target=self._serve, args=(ssl_ctx, ready, failure),
                                        name="rws-peer", daemon=True)
        self._thread.start()
        ready.wait(30)
        if failure:
            self._thread.join(5)
            raise failure[0]

    def _serve(self, ssl_ctx: Any, ready: threading.Event, failure: list[BaseException]
               ) -> None:
        loop = self._loop
        assert loop is not None
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._start_site(ssl_ctx))
        except BaseException as err:  # noqa: BLE001 - handed to start()
            failure.append(err)
            ready.set()
            loop.close()
            return
        log.info("rws %d.0 serving on port %d (%s)", self.version, self.port,
                 "https" if self.tls else "http")
        ready.set()
        loop.run_forever()
        loop.run_until_complete(self._shutdown())
        loop.close()

    async def _start_site(self, ssl_ctx: Any) -> None:
        app = web.Application(middlewares=[self._auth])
        self._routes(app)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._runner.setup()
        site = web.TCPSite(self._runner, "127.0.0.1", self.port, ssl_context=ssl_ctx)
        await site.start()
        server = getattr(site, "_server", None)
        self.port = server.sockets[0].getsockname()[1] if server else self.port

    async def _shutdown(self) -> None:
        for sub in list(self._subs.values()):
            if sub.get("ws") is not None:
                await sub["ws"].close()
        self._subs.clear()
        if self._runner is not None:
            await self._runner.cleanup()

    def stop(self) -> None:
        self._halt.set()
        for t in list(self._programs):
            t.join(30)
        if self._thread is not None and self._loop is not None:
            if self._thread.is_alive():
                self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(30)
        self._thread = None

    def _tls_context(self) -> Any:
        import ssl

        cert, key = self.workdir / "rws-cert.pem", self.workdir / "rws-key.pem"
        if not cert.exists():
            subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt",
                            "ec_paramgen_curve:prime256v1", "-nodes", "-keyout", str(key),
                            "-out", str(cert), "-days", "2", "-subj", "/CN=127.0.0.1",
                            "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost"],
                           check=True, capture_output=True, timeout=60)
        ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        ctx.load_cert_chain(cert, key)
        return ctx

    # -- authentication and sessions
    def _challenge(self, stale: bool = False) -> web.Response:
        if self.version == 2:
            head = f'Basic realm="{REALM}"'
        else:
            nonce = secrets.token_hex(16)
            self._nonces.add(nonce)
            head = (f'Digest realm="{REALM}", qop="auth", nonce="{nonce}", '
                    f'opaque="{secrets.token_hex(8)}", algorithm=MD5'
                    + (", stale=TRUE" if stale else ""))
        return web.Response(status=401, headers={"WWW-Authenticate": head})

    def _authorized(self, header: str, request: web.Request) -> bool | None:
        """True/False for a checked credential, None for a digest on an unknown nonce."""
        scheme, _, rest = header.partition(" ")
        if self.version == 2 and scheme == "Basic":
            try:
                user, _, pw = base64.b64decode(rest).decode().partition(":")
            except (ValueError, UnicodeDecodeError):
                return False
            return user == self.user and hmac.compare_digest(pw, self._password)
        if self.version == 1 and scheme == "Digest":
            f = {m.group(1): m.group(2) if m.group(2) is not None else m.group(3)
                 for m in _DIGEST_FIELD.finditer(rest)}
            if f.get("nonce") not in self._nonces:
                return None
            md5 = lambda s: hashlib.md5(s.encode()).hexdigest()  # noqa: E731 - RFC 7616 MD5
            ha1 = md5(f"{self.user}:{REALM}:{self._password}")
            ha2 = md5(f"{request.method}:{f.get('uri', '')}")
            want = md5(f"{ha1}:{f['nonce']}:{f.get('nc', '')}:{f.get('cnonce', '')}:"
                       f"{f.get('qop', '')}:{ha2}")
            return (f.get("username") == self.user and f.get("uri") == request.raw_path
                    and hmac.compare_digest(want, f.get("response", "")))
        return False

    @web.middleware
    async def _auth(self, request: web.Request, handler: Any) -> web.StreamResponse:
        if time.monotonic() < self._down_until:
            return _error(self.version, 503, "controller is starting")
        if request.cookies.get("-http-session-") in self._sessions:
            request[_SESSION] = request.cookies["-http-session-"]
            return await self._checked(request, handler)
        header = request.headers.get("Authorization")
        if not header:
            return self._challenge()
        self.auth_attempts += 1
        ok = self._authorized(header, request)
        if not ok:
            if ok is False:
                log.warning("login refused for user %r", self.user)
            return self._challenge(stale=ok is None)
        if self._busy > 0:
            self._busy -= 1
            log.info("login refused: too many sessions (503)")
            return _error(self.version, 503, "too many sessions")
        token = secrets.token_hex(16)
        self._sessions.add(token)
        self.issued.append(token)
        self.logins += 1
        log.info("session %d opened for user %r", self.logins, self.user)
        request[_SESSION] = token
        resp = await self._checked(request, handler)
        resp.set_cookie("-http-session-", token, httponly=True)
        resp.set_cookie("ABBCX", str(self.logins), httponly=True)
        return resp

    async def _checked(self, request: web.Request, handler: Any) -> web.StreamResponse:
        """The encoding each version demands: ``?json=1`` on 1.0, the v2.0 media types."""
        if request.path.startswith(("/rw", "/subscription")):
            if self.version == 1 and request.query.get("json") != "1":
                return _error(1, 400, "this fake answers JSON only (?json=1)")
            if self.version == 2 and self.api.accept not in request.headers.get("Accept", ""):
                return _error(2, 406, f"Accept must be {self.api.accept}")
            if (self.version == 2 and request.method == "POST"
                    and request.headers.get("Content-Type") != self.api.content_type):
                return _error(2, 415, f"Content-Type must be {self.api.content_type}")
        return await handler(request)

    # -- routes
    def _routes(self, app: web.Application) -> None:
        table: dict[tuple[str, str], dict[str | None, Any]] = {}
        a = self.api
        for which, method, fn in (
                ("mastership_request", "POST", self._mastership_request),
                ("mastership_release", "POST", self._mastership_release),
                ("loadmod", "POST", self._loadmod), ("symbol", "GET", self._get_symbol),
                ("symbol_set", "POST", self._set_symbol), ("execution", "GET", self._get_exec),
                ("exec_start", "POST", self._start), ("exec_stop", "POST", self._stop_exec),
                ("exec_resetpp", "POST", self._resetpp)):
            path, action = getattr(a, which)
            table.setdefault((method, path), {})[action] = fn
        for (method, path), actions in table.items():
            app.router.add_route(method, path, self._dispatch(actions))
        app.router.add_get("/", self._root)
        app.router.add_get("/logout", self._logout)
        app.router.add_post("/subscription", self._subscribe)
        app.router.add_delete("/subscription/{id}", self._unsubscribe)
        app.router.add_get("/poll/{id}", self._poll)
        app.router.add_route("*", "/fileservice/{path:.*}", self._files)

    def _dispatch(self, actions: dict[str | None, Any]) -> Any:
        async def handle(request: web.Request) -> web.StreamResponse:
            fn = actions.get(request.query.get("action"))
            if fn is None:
                return _error(self.version, 400, "unknown action")
            result: web.StreamResponse = await fn(request)
            return result
        return handle

    async def _root(self, request: web.Request) -> web.Response:
        return web.json_response(_state(self.version, [{"_type": "rw-service"}]))

    async def _logout(self, request: web.Request) -> web.Response:
        token = request.get(_SESSION)
        self._sessions.discard(token)
        if self._master == token:
            self._master = None
        log.info("session logged out")
        return web.Response(status=204)

    def _is_master(self, request: web.Request) -> bool:
        return self._master is not None and self._master == request.get(_SESSION)

    async def _mastership_request(self, request: web.Request) -> web.Response:
        if self._master not in (None, request.get(_SESSION)):
            return _error(self.version, 403, "mastership held by another client")
        self._master = request[_SESSION]
        return web.Response(status=204)

    async def _mastership_release(self, request: web.Request) -> web.Response:
        if self._is_master(request):
            self._master = None
        return web.Response(status=204)

    async def _loadmod(self, request: web.Request) -> web.Response:
        if not self._is_master(request):
            return _error(self.version, 403, "no RAPID mastership")
        form = await request.post()
        path = self._local(str(form.get("modulepath", "")))
        try:
            text = path.read_text() if path else ""
            if not re.match(rf"MODULE {PATH_MODULE}\b", text):
                raise ValueError("not the robid_path module")
            parse_rapid(text, self.core.robot.joint_types)
        except (OSError, ValueError) as err:
            return _error(self.version, 400, f"load error: {err}")
        self._loaded = text
        return web.Response(status=204)

    def _var(self, request: web.Request) -> str | None:
        m = request.match_info
        ok = m["task"] == "T_ROB1" and m["module"] == "robid" and m["var"] in VARS
        return m["var"] if ok else None

    async def _get_symbol(self, request: web.Request) -> web.Response:
        var = self._var(request)
        if var is None:
            return _error(self.version, 400, "no such symbol")
        value = '"' + self.vars[var].replace('"', '""') + '"'
        return web.json_response(_state(self.version, [{"_type": "rap-data", "value": value}]))

    async def _set_symbol(self, request: web.Request) -> web.Response:
        var = self._var(request)
        if var is None:
            return _error(self.version, 400, "no such symbol")
        if not self._is_master(request):
            return _error(self.version, 403, "no RAPID mastership")
        self.vars[var] = parse_rapid_string(str((await request.post()).get("value", "")))
        if var == "robid_params":
            self._receive_parameters(self.vars[var])
        self._notify_var(var)
        return web.Response(status=204)

    async def _get_exec(self, request: web.Request) -> web.Response:
        return web.json_response(_state(self.version, [{"_type": "rap-execution",
                                                        "ctrlexecstate": self.exec_state,
                                                        "cycle": "once"}]))

    async def _resetpp(self, request: web.Request) -> web.Response:
        if not self._is_master(request):
            return _error(self.version, 403, "no RAPID mastership")
        return web.Response(status=204)

    async def _start(self, request: web.Request) -> web.Response:
        if self.exec_state == "running":
            return _error(self.version, 400, "execution is already running")
        if self._master not in (None, request.get(_SESSION)):
            return _error(self.version, 403, "mastership held by another client")
        exp, nonce = self.vars["robid_exp"], self.vars["robid_nonce"]
        self._set_exec("running")
        t = threading.Thread(target=self._program, args=(exp, nonce, self._loaded),
                             name="rws-program", daemon=True)
        self._programs = [p for p in self._programs if p.is_alive()] + [t]
        t.start()
        return web.Response(status=204)

    async def _stop_exec(self, request: web.Request) -> web.Response:
        self._set_exec("stopped")
        return web.Response(status=204)

    # -- subscriptions
    async def _subscribe(self, request: web.Request) -> web.Response:
        form = await request.post()
        resources = [str(form[str(k)]) for k in form.getall("resources", []) if str(k) in form]
        known = {self._event_resource(v) for v in VARS} | {self.api.exec_event}
        if not resources or any(r not in known for r in resources):
            return _error(self.version, 400, "unknown subscription resource")
        sid = str(next(self._ids))
        self._subs[sid] = {"resources": resources, "ws": None, "silent": False,
                           "session": request[_SESSION]}
        scheme = "wss" if self.tls else "ws"
        return web.Response(status=201, headers={
            "Location": f"{scheme}://127.0.0.1:{self.port}/poll/{sid}"})

    async def _unsubscribe(self, request: web.Request) -> web.Response:
        sub = self._subs.pop(request.match_info["id"], None)
        if sub is None:
            return _error(self.version, 404, "no such subscription")
        if sub["ws"] is not None:
            await sub["ws"].close()
        return web.Response(status=204)

    async def _poll(self, request: web.Request) -> web.StreamResponse:
        sub = self._subs.get(request.match_info["id"])
        if sub is None or sub["session"] != request.get(_SESSION) or sub["ws"] is not None:
            return _error(self.version, 404, "no such subscription")
        offered = [p.strip() for p in request.headers.get("Sec-WebSocket-Protocol",
                                                          "").split(",")]
        if self.api.subprotocol not in offered:
            return _error(self.version, 400, "Unsupported Sec-WebSocket-Protocol")
        ws = web.WebSocketResponse(protocols=(self.api.subprotocol,))
        await ws.prepare(request)
        sub["ws"] = ws
        pinger = asyncio.create_task(self._ping_loop(ws, sub), name="rws-peer-ping")
        try:
            async for msg in ws:
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            pinger.cancel()
        return ws

    async def _ping_loop(self, ws: web.WebSocketResponse, sub: dict[str, Any]) -> None:
        while not ws.closed:
            await asyncio.sleep(self.ping_s)
            if not sub["silent"] and not ws.closed:
                await ws.ping()

    def _event_resource(self, var: str) -> str:
        return self.api.symbol_event.format(task="T_ROB1", module="robid", var=var)

    def _notify(self, resource: str, body: str) -> None:
        """Send an event to every subscriber of ``resource`` (call on the server's loop)."""
        for sid, sub in self._subs.items():
            ws = sub["ws"]
            if resource in sub["resources"] and ws is not None and not sub["silent"]:
                text = (f'<html><body><div class="state"><a href="subscription/{sid}" '
                        f'rel="group"></a><ul>{body}</ul></div></body></html>')
                asyncio.ensure_future(self._send(ws, text))

    @staticmethod
    async def _send(ws: web.WebSocketResponse, text: str) -> None:
        with contextlib.suppress(ConnectionError, RuntimeError):  # a closing socket
            await ws.send_str(text)

    def _notify_var(self, var: str) -> None:
        res = self._event_resource(var)
        self._notify(res, f'<li class="rap-value-ev"><a href="{res.split(";")[0]}" '
                          'rel="self"/></li>')

    def _set_exec(self, state: str) -> None:
        self.exec_state = state
        self._notify(self.api.exec_event,
                     '<li class="rap-ctrlexecstate-ev"><a href="/rw/rapid/execution;'
                     f'ctrlexecstate" rel="self"/><span class="ctrlexecstate">{state}</span>'
                     '</li>')

    def _in_loop(self, fn: Any, *args: Any) -> None:
        """Run ``fn`` on the server's loop (from a program thread) and wait for it."""
        assert self._loop is not None
        done = threading.Event()

        def call() -> None:
            try:
                fn(*args)
            finally:
                done.set()
        if not self._loop.is_closed():
            self._loop.call_soon_threadsafe(call)
            done.wait(10)

    # -- the file service
    def _local(self, remote: str) -> Path | None:
        if not remote.startswith("$HOME/") or ".." in remote.split("/"):
            return None
        path = (self.home / remote[len("$HOME/"):]).resolve()
        return path if path.is_relative_to(self.home.resolve()) else None

    async def _files(self, request: web.Request) -> web.StreamResponse:
        path = self._local(request.match_info["path"])
        if path is None:
            return _error(self.version, 403, "outside $HOME")
        if request.method == "PUT":
            data = await request.read()
            await asyncio.to_thread(self._write, path, data)
            return web.Response(status=201)
        if request.method == "GET" and path.is_file():
            return web.Response(body=await asyncio.to_thread(path.read_bytes),
                                content_type="application/octet-stream")
        if request.method == "DELETE" and path.is_file():
            path.unlink()
            return web.Response(status=204)
        return _error(self.version, 404, "no such file")

    @staticmethod
    def _write(path: Path, data: bytes) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, data)

    def _receive_parameters(self, remote: str) -> None:
        """The robid module loads the set named in ``robid_params`` and acknowledges it."""
        if not remote or (self.core.fault == "no_param_ack" and self.core.take_fault()):
            return
        path = self._local(remote)
        tag = Path(remote).stem.rsplit(".", 1)[-1]
        try:
            if path is None:
                raise RobidError(f"{remote}: not on the controller's disk")
            self.core.receive_parameters(path.read_bytes())
            self.vars["robid_params_ack"] = f"{tag} OK"
        except (OSError, RobidError) as err:
            self.vars["robid_params_ack"] = f"{tag} ERR {str(err)[:80]}"
        self._notify_var("robid_params_ack")

    # -- the robid RAPID module's main, on the plant
    def _program(self, exp: str, nonce: str, module: str) -> None:
        def finish(done: str | None) -> None:
            if done is not None:
                self.vars["robid_done"] = done
                self._notify_var("robid_done")
            self._set_exec("stopped")

        if f"experiment {exp}," not in module:  # %robid_move% runs whatever is loaded
            self._in_loop(finish, error_value(nonce, "loaded module is not this experiment's"))
            return
        try:
            csv = (self.home / "robid" / f"{exp}.traj.csv").read_bytes()
            header = (self.home / "robid" / f"{exp}.traj.yaml").read_bytes()
        except OSError as err:
            self._in_loop(finish, error_value(nonce, f"trajectory: {err.strerror}"))
            return
        res = self.core.run(exp, nonce, csv, header)
        if res.fault in ("never_answer", "die"):
            if res.fault == "die":
                self.core.die()
                self.died.set()
            self._halt.wait()  # hangs until stopped (withdraw) or the peer stops
            return
        if res.fault == "exec_error":  # motion supervision: execution stops, no 'done'
            self._in_loop(finish, None)
            return
        if res.error is not None:
            self._in_loop(finish, error_value(nonce, res.error))
            return
        if res.fault in ("restart", "silent_ws"):  # while the daemon waits on its socket
            end = time.monotonic() + 10
            while (not any(sub["ws"] is not None for sub in list(self._subs.values()))
                   and time.monotonic() < end and not self._halt.wait(0.01)):
                pass
        if res.fault == "restart":
            self._in_loop(self._restart)
        elif res.fault == "silent_ws":
            self._in_loop(self._silence)
            # the program ends once the daemon has noticed and subscribed again: finishing
            # while it still asks after its first subscription would never test the silence
            end = time.monotonic() + 10
            while (not any(sub["ws"] is not None and not sub["silent"]
                           for sub in list(self._subs.values()))
                   and time.monotonic() < end and not self._halt.wait(0.01)):
                pass
        self._write(self.home / log_file(exp, nonce)[len("$HOME/"):], res.delivered)
        done = done_value(nonce, res.sha256, len(res.log))
        if res.fault == "stale_semaphore":  # an answer to an attempt that no longer exists
            self._in_loop(self._set_var, "robid_done", done_value("0stale0", "0" * 64, 1))
        self._in_loop(finish, done)
        if res.fault == "answer_twice":  # the same answer written a second time
            self._in_loop(self._set_var, "robid_done", done)

    def _set_var(self, var: str, value: str) -> None:
        self.vars[var] = value
        self._notify_var(var)

    def _restart(self) -> None:
        log.info("controller restarts (fault restart)")
        self._down_until = time.monotonic() + self.restart_s
        self._sessions.clear()
        self._nonces.clear()
        self._master = None
        for sub in self._subs.values():
            if sub["ws"] is not None:
                asyncio.ensure_future(sub["ws"].close())
        self._subs.clear()

    def _silence(self) -> None:
        log.info("websockets go silent (fault silent_ws)")
        for sub in self._subs.values():
            sub["silent"] = True
