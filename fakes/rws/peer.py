"""The controller side of the RWS link: an RWS 1.0 or 2.0 look-alike (aiohttp server and
websocket subscriptions on 127.0.0.1, a random port) serving the resources of
``rws_resources.py`` (written from ABB's RWS manuals, not from the driver), running each
started program on the fake controller's plant as the robid RAPID module would.

Faults beyond the core's: ``restart`` (the controller restarts mid-program: sockets, sessions
and subscriptions gone, 503 for a moment, the program finishes meanwhile), ``silent_ws`` (the
socket stays open but carries neither pings nor events; the program ends once the daemon
subscribed again), ``exec_error`` (execution stops with
no 'done'), ``session_limit`` (503 for the first ``fault_count`` logins), ``bad_credentials``
(the daemon gets a wrong password). Hostile ones, while a faulted program runs (it runs on
until execution is stopped): ``garbage_state`` (the execution state answers an HTML page),
``wrong_shape`` (it answers JSON of another shape), ``endless_log`` (the log download never
ends), ``redirect`` (the subscription's websocket and the file service answer 302 to
``redirect_to``). Every stop request is kept in ``stops`` (its wall-clock time). The server logs
no secret: no password, no cookie.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import re
import secrets
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from robid_link.atomic import atomic_write
from robid_link.exceptions import RobidError
from robid_link.fakes.controller import ControllerCore, Peer
from robid_link.fakes.rws.login import Login, tls_context, write_credentials
from robid_link.fakes.rws.resources import (
    DIALECTS,
    PATH_MODULE,
    RAPID_STRING_MAX,
    ROBID_MODULE,
    ROBID_TASK,
    ROBID_VARS,
    check_path_module,
    done_value,
    error_value,
    event_page,
    exec_event,
    rapid_string_text,
    rapid_string_value,
    size_value,
    value_event,
)

__all__ = ["RwsPeer"]

log = logging.getLogger("robid.fake_controller.rws")

_SESSION = web.RequestKey("session", str)
#: a controller path (loadmod's modulepath, robid_params): the HOME variable, any case
_CONTROLLER_HOME = re.compile(r"^\$home/", re.I)
_ROBID_DIR = "robid"
_ERR = -1073445879  # the RWS return code the fake gives every refusal


class RwsPeer(Peer):
    """Serve RWS ``version`` (1 or 2) from a thread with its own event loop; TLS (a
    self-signed certificate made with the ``openssl`` tool) by default on 2.0. Options:
    ``version``, ``tls`` (auto | true | false), ``ping_interval_s``, ``restart_s``."""

    driver = "abb_rws"
    faults = ("restart", "silent_ws", "exec_error", "session_limit", "bad_credentials",
              "garbage_state", "wrong_shape", "endless_log", "redirect")
    #: the faults that play the controller as hostile (the program runs until stopped)
    hostile = ("garbage_state", "wrong_shape", "endless_log", "redirect")
    #: the contract suite runs once per RWS version (2.0: HTTPS, Basic auth, hal+json)
    contract_variants: tuple[dict[str, Any], ...] = ({"version": 1}, {"version": 2})

    def __init__(self, core: ControllerCore, workdir: Path, *, version: int = 1,
                 tls: str | bool = "auto", ping_interval_s: float = 30.0,
                 restart_s: float = 0.5, port: int = 0,
                 redirect_to: str = "http://127.0.0.2:9/elsewhere") -> None:
        super().__init__(core, workdir)
        if version not in (1, 2):
            raise ValueError(f"version: expected 1 or 2, got {version!r}")
        self.version, self.dialect = version, DIALECTS[version]
        #: set by tests: called with ("request", request, body) as a request arrives and with
        #: ("response", request, response) once it is answered (a recording peer)
        self.tap: Callable[[str, web.Request, Any], None] | None = None
        self.ping_s, self.restart_s, self.port = float(ping_interval_s), restart_s, port
        self.home = self.workdir / "HOME"
        (self.home / "robid").mkdir(parents=True, exist_ok=True)
        if tls == "auto":
            tls = version == 2 and shutil.which("openssl") is not None
        self.tls = bool(tls)
        self.user, self._password = "robid", secrets.token_urlsafe(12)
        self.credentials = self.workdir / "rws-credentials"
        wrong = core.fault == "bad_credentials"
        write_credentials(self.credentials, self.user, ("wrong-" if wrong else "")
                          + self._password)
        self.auth_attempts = self.logins = 0
        self.issued: list[str] = []  # session cookies handed out (tests look for leaks)
        self._busy = core.faults_left if core.fault == "session_limit" else 0
        self._sessions: set[str] = set()
        self.login = Login(version, self.user, self._password)
        self._master: str | None = None
        self.vars = dict.fromkeys(ROBID_VARS, "")
        self.exec_state = "stopped"
        self._loaded = ""  # the experiment whose module is loaded (its file's name)
        self._subs: dict[str, dict[str, Any]] = {}
        self._ids = itertools.count(1)
        self._down_until = 0.0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self._programs: list[threading.Thread] = []
        self._halt = threading.Event()
        self._lock = threading.Lock()
        self.redirect_to = redirect_to
        self.stops: list[float] = []  # time.time() of every stop request
        self._stopped = threading.Event()  # set by a stop request: a hanging program ends
        self._hostile: str | None = None  # the hostile fault of the program running now

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
        ssl_ctx = tls_context(self.workdir) if self.tls else None
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
        app = web.Application(middlewares=[self._record, self._auth])
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

    # -- authentication and sessions
    def _answer(self, status: int, items: list[dict[str, Any]]) -> web.Response:
        """A JSON answer in this version's envelope."""
        ctype = "application/hal+json" if self.version == 2 else "application/json"
        return web.json_response(self.dialect.envelope(items), status=status,
                                 content_type=ctype)

    def _refuse(self, status: int, msg: str) -> web.Response:
        return web.json_response(self.dialect.error(_ERR, msg), status=status)

    @web.middleware
    async def _record(self, request: web.Request, handler: Any) -> web.StreamResponse:
        """Hands every request and its answer to ``tap`` (tests), before and after."""
        tap = self.tap
        if tap is None:
            return await handler(request)
        tap("request", request, await request.read())
        resp: web.StreamResponse = await handler(request)
        tap("response", request, resp)
        return resp

    @web.middleware
    async def _auth(self, request: web.Request, handler: Any) -> web.StreamResponse:
        if time.monotonic() < self._down_until:
            return self._refuse(503, "controller is starting")
        if request.cookies.get("-http-session-") in self._sessions:
            request[_SESSION] = request.cookies["-http-session-"]
            return await self._checked(request, handler)
        header = request.headers.get("Authorization")
        if not header:
            return web.Response(status=401, headers={"WWW-Authenticate": self.login.challenge()})
        self.auth_attempts += 1
        ok = self.login.check(header, request.method, request.raw_path)
        if not ok:
            if ok is False:
                log.warning("login refused for user %r", self.user)
            return web.Response(status=401, headers={
                "WWW-Authenticate": self.login.challenge(stale=ok is None)})
        if self._busy > 0:
            self._busy -= 1
            log.info("login refused: too many sessions (503)")
            return self._refuse(503, "too many sessions")
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
        """The encodings each version demands of the resources that answer or take a body:
        ``?json=1`` for a JSON answer on 1.0; on 2.0 the v2.0 media types (Accept of an answer
        under /rw or /subscription, Content-Type of a form and of a file upload)."""
        d, path = self.dialect, request.path
        rws = path.startswith(("/rw", "/subscription")) and not path.startswith("/poll")
        if d.json_query and rws and request.method == "GET" and request.query.get("json") != "1":
            return self._refuse(400, "this fake answers JSON only (?json=1)")
        if d.accept is not None and rws and request.method in ("GET", "POST") and (
                d.accept not in request.headers.get("Accept", "")):
            return self._refuse(406, f"Accept must be {d.accept}")
        if d.form is not None and rws and request.method == "POST" and (
                request.headers.get("Content-Type") != d.form):
            return self._refuse(415, f"Content-Type must be {d.form}")
        if d.uploads and path.startswith("/fileservice/") and request.method == "PUT" and (
                request.headers.get("Content-Type") not in d.uploads):
            return self._refuse(415, f"Content-Type must be one of {', '.join(d.uploads)}")
        return await handler(request)

    # -- routes
    def _routes(self, app: web.Application) -> None:
        table: dict[tuple[str, str], dict[str | None, Any]] = {}
        for method, path, action, name in self.dialect.routes:
            table.setdefault((method, path), {})[action] = getattr(self, f"_{name}")
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
                return self._refuse(400, "unknown action")
            result: web.StreamResponse = await fn(request)
            return result
        return handle

    async def _root(self, request: web.Request) -> web.Response:
        return self._answer(200, [{"_type": "rw-service", "_title": "rw"}])

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
            return self._refuse(403, "mastership held by another client")
        self._master = request[_SESSION]
        return web.Response(status=204)

    async def _mastership_release(self, request: web.Request) -> web.Response:
        if self._is_master(request):
            self._master = None
        return web.Response(status=204)

    async def _loadmod(self, request: web.Request) -> web.Response:
        """Load a module file from the controller's disk (modulepath, replace); RAPID
        mastership required. Only the robid_path module of an experiment loads here."""
        if not self._is_master(request):
            return self._refuse(403, "no RAPID mastership")
        if request.match_info["task"] != ROBID_TASK:
            return self._refuse(404, "no such task")
        form = await request.post()
        remote = str(form.get("modulepath", ""))
        path = self._controller_path(remote)
        if path is None or path.parent != self.home / _ROBID_DIR or path.suffix != ".mod":
            return self._refuse(400, f"load error: {remote!r} is no module in $HOME/robid")
        if str(form.get("replace", "false")) != "true" and self._loaded:
            return self._refuse(400, f"load error: module {PATH_MODULE} already loaded")
        try:
            why = check_path_module(await asyncio.to_thread(path.read_text))
        except (OSError, UnicodeDecodeError) as err:
            why = str(err)
        if why is not None:
            return self._refuse(400, f"load error: {why}")
        self._loaded = path.stem
        return web.Response(status=204)

    def _var(self, request: web.Request) -> str | None:
        m = request.match_info
        ok = m["task"] == ROBID_TASK and m["module"] == ROBID_MODULE and m["var"] in ROBID_VARS
        return m["var"] if ok else None

    async def _get_symbol(self, request: web.Request) -> web.Response:
        var = self._var(request)
        if var is None:
            return self._refuse(400, "no such symbol")
        return self._answer(200, [{"_type": "rap-data",
                                   "_title": f"RAPID/{ROBID_TASK}/{ROBID_MODULE}/{var}",
                                   "value": rapid_string_value(self.vars[var])}])

    async def _set_symbol(self, request: web.Request) -> web.Response:
        var = self._var(request)
        if var is None:
            return self._refuse(400, "no such symbol")
        if not self._is_master(request):
            return self._refuse(403, "no RAPID mastership")
        text = rapid_string_text(str((await request.post()).get("value", "")))
        if text is None or len(text) > 80:
            return self._refuse(400, "value is not a RAPID string (\"…\", at most 80 characters)")
        self.vars[var] = text
        if var == "robid_params":
            self._receive_parameters(text)
        self._notify_var(var)
        return web.Response(status=204)

    async def _get_execution(self, request: web.Request) -> web.Response:
        if self._hostile == "garbage_state":
            return web.Response(status=200, text="<html><body>controller busy</body></html>",
                                content_type="text/html")
        if self._hostile == "wrong_shape":
            return web.json_response({"_embedded": {"_state": {"ctrlexecstate": [1, 2]}},
                                      "state": "running"})
        return self._answer(200, [{"_type": "rap-execution", "_title": "execution",
                                   "ctrlexecstate": self.exec_state, "cycle": "once"}])

    async def _resetpp(self, request: web.Request) -> web.Response:
        if not self._is_master(request):
            return self._refuse(403, "no RAPID mastership")
        return web.Response(status=204)

    async def _start(self, request: web.Request) -> web.Response:
        if self.exec_state == "running":
            return self._refuse(400, "execution is already running")
        if self._master not in (None, request.get(_SESSION)):
            return self._refuse(403, "mastership held by another client")
        form = await request.post()
        if form.get("cycle", "asis") not in ("once", "forever", "asis", "oncedone"):
            return self._refuse(400, "cycle: expected once, forever, asis or oncedone")
        exp, nonce = self.vars["robid_exp"], self.vars["robid_nonce"]
        self._stopped.clear()
        # a controller that answers garbage does so from the start of the faulted program
        self._hostile = (self.core.fault if self.core.fault in self.hostile
                         and self.core.faults_left > 0 else None)
        self._set_exec("running")
        t = threading.Thread(target=self._program, args=(exp, nonce, self._loaded),
                             name="rws-program", daemon=True)
        self._programs = [p for p in self._programs if p.is_alive()] + [t]
        t.start()
        return web.Response(status=204)

    async def _stop(self, request: web.Request) -> web.Response:
        self.stops.append(time.time())
        log.info("execution stopped by request")
        self._stopped.set()
        self._set_exec("stopped")
        return web.Response(status=204)

    # -- subscriptions
    async def _subscribe(self, request: web.Request) -> web.Response:
        """``resources=<k>`` (repeated), ``<k>=<resource uri>``, ``<k>-p=<priority 0-2>``."""
        form = await request.post()
        keys = [str(k) for k in form.getall("resources", [])]
        resources = [str(form.get(k, "")) for k in keys]
        known = {self.dialect.variable_resource(v) for v in ROBID_VARS}
        known.add(self.dialect.exec_resource)
        if not keys or any(r not in known for r in resources) or any(
                str(form.get(f"{k}-p", "")) not in ("0", "1", "2") for k in keys):
            return self._refuse(400, "unknown subscription resource or priority")
        sid = str(next(self._ids))
        self._subs[sid] = {"resources": resources, "ws": None, "silent": False,
                           "session": request[_SESSION], "sent": None}
        scheme = "wss" if self.tls else "ws"
        return web.Response(status=201, headers={
            "Location": f"{scheme}://127.0.0.1:{self.port}/poll/{sid}"})

    async def _unsubscribe(self, request: web.Request) -> web.Response:
        sub = self._subs.pop(request.match_info["id"], None)
        if sub is None:
            return self._refuse(404, "no such subscription")
        if sub["ws"] is not None:
            await sub["ws"].close()
        return web.Response(status=204)

    def _redirect(self) -> web.Response:
        return web.Response(status=302, headers={"Location": self.redirect_to})

    async def _poll(self, request: web.Request) -> web.StreamResponse:
        if self._hostile == "redirect":
            return self._redirect()
        sub = self._subs.get(request.match_info["id"])
        if sub is None or sub["session"] != request.get(_SESSION) or sub["ws"] is not None:
            return self._refuse(404, "no such subscription")
        offered = [p.strip() for p in request.headers.get("Sec-WebSocket-Protocol",
                                                          "").split(",")]
        if self.dialect.subprotocol not in offered:
            return self._refuse(400, "Unsupported Sec-WebSocket-Protocol")
        ws = web.WebSocketResponse(protocols=(self.dialect.subprotocol,))
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

    def _notify(self, resource: str, items: str) -> None:
        """An event (XHTML, as RWS sends them) to every subscriber of ``resource``, in order
        per socket (call on the server's loop)."""
        for sid, sub in self._subs.items():
            ws = sub["ws"]
            if resource in sub["resources"] and ws is not None and not sub["silent"]:
                sub["sent"] = asyncio.ensure_future(self._send(sub["sent"], ws,
                                                               event_page(sid, items)))

    @staticmethod
    async def _send(before: asyncio.Future[None] | None, ws: web.WebSocketResponse,
                    text: str) -> None:
        if before is not None:
            await asyncio.wait([before])
        with contextlib.suppress(ConnectionError, RuntimeError):  # a closing socket
            await ws.send_str(text)

    def _notify_var(self, var: str) -> None:
        res = self.dialect.variable_resource(var)
        self._notify(res, value_event(res, var, rapid_string_value(self.vars[var])))

    def _set_exec(self, state: str) -> None:
        self.exec_state = state
        self._notify(self.dialect.exec_resource, exec_event(self.dialect.exec_resource, state))

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
        """A file-service path (``<HOME variable>/…``, spelled as this version wants it)."""
        home = self.dialect.home + "/"
        return self._inside(remote[len(home):]) if remote.startswith(home) else None

    def _controller_path(self, remote: str) -> Path | None:
        """A path as RAPID and loadmod name it (``$HOME/…``; the variable in any case)."""
        m = _CONTROLLER_HOME.match(remote)
        return self._inside(remote[m.end():]) if m else None

    def _inside(self, rel: str) -> Path | None:
        if ".." in rel.split("/"):
            return None
        path = (self.home / rel).resolve()
        return path if path.is_relative_to(self.home.resolve()) else None

    async def _files(self, request: web.Request) -> web.StreamResponse:
        path = self._local(request.match_info["path"])
        if path is None:
            return self._refuse(403, f"outside {self.dialect.home}")
        if request.method == "PUT":
            data = await request.read()
            await asyncio.to_thread(self._write, path, data)
            return web.Response(status=201)
        if request.method == "GET" and self._hostile == "redirect":
            return self._redirect()
        if request.method == "GET" and self._hostile == "endless_log" and path.is_file():
            return await self._endless(request)
        if request.method == "GET" and path.is_file():
            return web.Response(body=await asyncio.to_thread(path.read_bytes),
                                content_type="application/octet-stream")
        if request.method == "DELETE" and path.is_file():
            path.unlink()
            return web.Response(status=204)
        return self._refuse(404, "no such file")

    async def _endless(self, request: web.Request) -> web.StreamResponse:
        """A log that never ends (a logger left running into the file being served)."""
        resp = web.StreamResponse(headers={"Content-Type": "application/octet-stream"})
        await resp.prepare(request)
        row = b"0.001,0.1,0.2,0.3,1.5,2.5,3.5\n" * 2048
        with contextlib.suppress(ConnectionError, RuntimeError):
            while not self._halt.is_set():
                await resp.write(row)
        return resp

    @staticmethod
    def _write(path: Path, data: bytes) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, data)

    def _receive_parameters(self, remote: str) -> None:
        """The robid module loads the set named in ``robid_params`` and acknowledges it in
        ``robid_params_ack``: ``<tag> OK`` or ``<tag> ERR <reason>``, the tag being the part of
        the file name before ``.json`` after the robot's name."""
        if not remote or (self.core.fault == "no_param_ack" and self.core.take_fault()):
            return
        path = self._controller_path(remote)
        tag = Path(remote).stem.rsplit(".", 1)[-1]
        try:
            if path is None:
                raise RobidError(f"{remote}: not on the controller's disk")
            self.core.receive_parameters(path.read_bytes())
            self.vars["robid_params_ack"] = f"{tag} OK"
        except (OSError, RobidError) as err:
            self.vars["robid_params_ack"] = f"{tag} ERR {' '.join(str(err).split())}"[:80]
        self._notify_var("robid_params_ack")

    # -- the robid RAPID module's main, on the plant
    def _program(self, exp: str, nonce: str, loaded: str) -> None:
        """main of the robid module: clear robid_done, run the loaded robid_path (late
        binding), close the log, then ``robid_size`` := ``<nonce> <size>`` and ``robid_done``
        := ``<nonce> <sha256>`` (or ``ERR <nonce> <text>``); execution stops (README
        sketch)."""
        def finish(done: str | None, size: str | None = None) -> None:
            if size is not None:  # the size first: 'done' is the mark that all is there
                self._set_var("robid_size", size)
            if done is not None:
                self._set_var("robid_done", done)
            self._set_exec("stopped")

        if loaded != exp:  # %robid_move% runs whatever is loaded
            self._in_loop(finish, error_value(nonce, "loaded module is not this experiment's"))
            return
        folder = self.home / _ROBID_DIR
        try:
            csv = (folder / f"{exp}.traj.csv").read_bytes()
            header = (folder / f"{exp}.traj.yaml").read_bytes()
        except OSError as err:
            self._in_loop(finish, error_value(nonce, f"trajectory: {err.strerror}"))
            return
        res = self.core.run(exp, nonce, csv, header)
        if res.fault in ("garbage_state", "wrong_shape", "redirect"):
            self._until_stopped()
            return
        if res.fault in ("never_answer", "die"):
            if res.fault == "die":
                self.core.die()
                self.died.set()
            self._until_stopped()  # hangs until stopped (withdraw) or the peer stops
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
        self._write(folder / f"{exp}.{nonce}.log.csv", res.delivered)
        done = done_value(nonce, res.sha256)
        if res.fault == "stale_semaphore":  # an answer to an attempt that no longer exists
            self._in_loop(self._set_var, "robid_done", done_value("0stale0", "0" * 64))
        self._in_loop(finish, done, size_value(nonce, len(res.log)))
        if res.fault == "answer_twice":  # the same answer written a second time
            self._in_loop(self._set_var, "robid_done", done)

    def _until_stopped(self) -> None:
        """A program that runs until execution is stopped (or the peer stops)."""
        while not self._halt.is_set() and not self._stopped.wait(0.05):
            pass
        self._hostile = None

    def _set_var(self, var: str, value: str) -> None:
        """RAPID's own write of a PERS string: one over 80 characters is an execution error
        (ERRNO ERR_STRTOOLNG), which the robid module's ERROR handler reports in
        ``robid_done``."""
        if len(value) > RAPID_STRING_MAX:
            log.error("RAPID: %s: string of %d characters (at most %d)", var, len(value),
                      RAPID_STRING_MAX)
            var, value = "robid_done", error_value(self.vars["robid_nonce"],
                                                   f"ERR_STRTOOLNG writing {var}")
        self.vars[var] = value
        self._notify_var(var)

    def _restart(self) -> None:
        log.info("controller restarts (fault restart)")
        self._down_until = time.monotonic() + self.restart_s
        self._sessions.clear()
        self.login.forget()
        self._master = None
        for sub in self._subs.values():
            if sub["ws"] is not None:
                asyncio.ensure_future(sub["ws"].close())
        self._subs.clear()

    def _silence(self) -> None:
        log.info("websockets go silent (fault silent_ws)")
        for sub in self._subs.values():
            sub["silent"] = True

