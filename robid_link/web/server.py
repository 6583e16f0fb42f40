"""The operator's page over HTTP (aiohttp): runs, a run's report, comparisons, trends and
parameter sets, each page with its JSON twin under ``/api/``; actions are POSTs that need the
token and, from a form, the CSRF cookie. ``robid web`` serves it read-only from the state dir;
the daemon serves it with actions when its config has ``web: {listen: …}``."""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import logging
import os
import secrets
import ssl
import stat
from collections.abc import Awaitable, Callable
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from aiohttp import web

from robid_link.config import DaemonConfig, WebConfig
from robid_link.exceptions import ConfigError, RobidError
from robid_link.link.store import open_reader
from robid_link.web import pages, views

__all__ = ["WebServer", "make_app", "parse_listen", "load_token", "DEFAULT_LISTEN",
           "TOKEN_NAME"]

log = logging.getLogger("robid.web")

DEFAULT_LISTEN = "127.0.0.1:8765"
TOKEN_NAME = "web.token"
CSRF_COOKIE = "robid_csrf"
#: the CSRF value of the request being served (the cookie's, or the one it is given now)
_CSRF: ContextVar[str] = ContextVar("robid_csrf", default="")
Actions = Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]
#: the action routes and the control request each one makes
_ACTIONS = {"start": ("campaign",), "cancel": ("run_id",), "resume": ("run_id",),
            "approve": ("robot", "set")}
_HEADERS = {"Content-Security-Policy": "default-src 'none'; script-src 'unsafe-inline'; "
            "style-src 'unsafe-inline'; img-src data:; connect-src 'self'; form-action 'self'; "
            "frame-ancestors 'none'; base-uri 'none'",
            "X-Content-Type-Options": "nosniff", "Referrer-Policy": "same-origin"}


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8765`` for IPv6; port 0: the system picks one) → (host, port)."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ConfigError(f"web.listen: expected HOST:PORT (e.g. {DEFAULT_LISTEN}), "
                          f"got {text!r}")
    return host, int(port)


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a name: only localhost is known to stay on the machine
        return False


class _Hosts:
    """The names a request may give in its Host header, against DNS rebinding (a foreign
    page whose name resolves to this address): the listen host, the loopback names and
    ``web.hosts``; when listening on every address, any address too (never another name)."""

    def __init__(self, listen_host: str | None, extra: tuple[str, ...]) -> None:
        listen = _normal(listen_host or "127.0.0.1")
        self.any_address = listen in ("0.0.0.0", "::")
        self.names = {_normal(n) for n in ("localhost", *extra, listen)}
        self.shown = ", ".join(dict.fromkeys([listen, "localhost", *extra]))

    def allows(self, host: str) -> bool:
        name = _normal(_without_port(host))
        if name in self.names:
            return True
        try:
            addr = ipaddress.ip_address(name)
        except ValueError:
            return False
        return addr.is_loopback or self.any_address


def _without_port(host: str) -> str:
    host = host.strip()
    if host.startswith("["):  # [v6]:port
        return host[1:].partition("]")[0]
    return host.rpartition(":")[0] if host.count(":") == 1 else host


def _normal(name: str) -> str:
    """A host name lower-cased without its trailing dot; an address in its short form."""
    name = name.lower().rstrip(".")
    try:
        return str(ipaddress.ip_address(name))
    except ValueError:
        return name


def load_token(web_cfg: WebConfig, state_dir: Path, *, create: bool) -> str | None:
    """The actions' token: ``web.token``, else the file ``web.token_file`` (default
    ``web.token`` in the state dir), which must be private (0600); ``create`` makes the
    default file when it is missing (the daemon does, once)."""
    if web_cfg.token:
        return web_cfg.token
    path = web_cfg.token_file or state_dir / TOKEN_NAME
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except FileNotFoundError:
        if not create or web_cfg.token_file is not None:
            if web_cfg.token_file is not None:
                raise ConfigError(f"web.token_file: {path} not found") from None
            return None
        token = secrets.token_urlsafe(32)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(token + "\n")
        log.info("web: token for actions written to %s (mode 0600)", path)
        return token
    except OSError as err:
        raise ConfigError(f"web.token_file: {path}: {err.strerror}") from err
    with os.fdopen(fd) as f:
        mode = os.fstat(f.fileno()).st_mode
        if not stat.S_ISREG(mode):
            raise ConfigError(f"web.token_file: {path} is not a regular file")
        if mode & 0o077:
            raise ConfigError(f"web.token_file: {path} is readable by others (mode "
                              f"{stat.S_IMODE(mode):04o}; chmod 600 it)")
        token = f.read(4096).strip()
    if len(token) < 16:
        raise ConfigError(f"web.token_file: {path} holds under 16 characters")
    return token


def _tls(web_cfg: WebConfig) -> ssl.SSLContext | None:
    if web_cfg.tls_cert is None or web_cfg.tls_key is None:
        return None
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    try:
        ctx.load_cert_chain(web_cfg.tls_cert, web_cfg.tls_key)
    except (OSError, ssl.SSLError) as err:
        raise ConfigError(f"web.tls_cert/tls_key: {web_cfg.tls_cert}, {web_cfg.tls_key}: "
                          f"not a certificate and its key ({err})") from err
    return ctx


class _App:
    """The handlers; every read opens the store read-only in a worker thread."""

    def __init__(self, cfg: DaemonConfig, robot: str, actions: Actions | None,
                 token: str | None, tls: bool, hosts: _Hosts) -> None:
        self.cfg, self.robot, self.actions, self.token, self.tls = cfg, robot, actions, token, tls
        self.hosts = hosts

    async def read(self, fn: Callable[..., Any], *args: Any) -> Any:
        def work() -> Any:
            with open_reader(self.cfg, self.robot) as store:
                return fn(store, *args)
        return await asyncio.to_thread(work)

    # ----------------------------------------------------------------- pages and their twins
    def _context(self, request: web.Request) -> dict[str, Any]:
        return {"robot": self.robot, "actions": self.actions is not None,
                "csrf": _CSRF.get(), "campaigns": sorted(self.cfg.campaigns),
                "state_dir": str(self.cfg.state_dir)}

    async def runs(self, request: web.Request) -> web.StreamResponse:
        view = await self.read(views.runs_view, self.robot, _limit(request))
        if request.path.startswith("/api/"):
            return web.json_response(view)
        fragment = request.query.get("fragment") == "runs"
        return _html(pages.runs_page(view, self._context(request), fragment=fragment))

    async def run(self, request: web.Request) -> web.StreamResponse:
        view = await self.read(views.run_view, request.match_info["run_id"], self.robot)
        if request.path.startswith("/api/"):
            return web.json_response(view)
        return _html(await asyncio.to_thread(pages.run_page, view, self._context(request)))

    async def compare(self, request: web.Request) -> web.StreamResponse:
        a, b = request.query.get("a"), request.query.get("b")
        view = await self.read(views.compare_view, a, b) if a and b else None
        if request.path.startswith("/api/"):
            if view is None:
                raise web.HTTPBadRequest(text="compare: give ?a=RUN&b=RUN (or robot:NAME)\n")
            return web.json_response(view)
        recent = await self.read(views.runs_view, self.robot, 50)
        return _html(pages.compare_page(view, recent, self._context(request), {"a": a, "b": b}))

    async def trend(self, request: web.Request) -> web.StreamResponse:
        robot = request.query.get("robot", self.robot)
        view = await self.read(views.trend_view, robot)
        if request.path.startswith("/api/"):
            return web.json_response(view)
        return _html(pages.trend_page(view, self._context(request)))

    async def params(self, request: web.Request) -> web.StreamResponse:
        robots = await self.read(views.robots_in, self.robot)
        view = await self.read(views.params_view, robots)
        if request.path.startswith("/api/"):
            return web.json_response(view)
        return _html(pages.params_page(view, self._context(request)))

    async def fleet(self, request: web.Request) -> web.StreamResponse:
        view = await self.read(views.fleet_page_view)
        if request.path.startswith("/api/"):
            return web.json_response(view)
        return _html(pages.fleet_page(view, self._context(request)))

    # ----------------------------------------------------------------- actions
    async def act(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["action"]
        if name not in _ACTIONS:
            raise web.HTTPNotFound(text=f"no action {name!r}\n")
        form = await request.post()
        bearer = request.headers.get("Authorization", "")
        given = bearer.removeprefix("Bearer ").strip() if bearer.startswith("Bearer ") \
            else str(form.get("token", ""))
        if self.actions is None:
            return _refuse(request, "read-only page (robid web): actions are served by the "
                           "daemon's own page (web.listen in its config)")
        if not self.token or not given or not hmac.compare_digest(given, self.token):
            return _refuse(request, "token missing or wrong")
        if not bearer and not self._csrf_ok(request, form):
            return _refuse(request, "CSRF check failed (reload the page and submit again)")
        req = {"cmd": {"start": "start", "cancel": "cancel", "resume": "resume",
                       "approve": "params_approve"}[name],
               **{k: str(form[k]) for k in _ACTIONS[name] if form.get(k)}, "by": "web"}
        if name == "start":  # unattended: the page may be far from the cell
            req["trigger"] = "web"
        try:
            ans = await self.actions(req)
        except RobidError as err:
            return _answer(request, 400, {"ok": False, "error": str(err)})
        log.info("web action %s %s: %s", name, {k: v for k, v in req.items() if k != "cmd"},
                 ans.get("message") or ans.get("run_id") or "ok")
        return _answer(request, 200, ans)

    def _csrf_ok(self, request: web.Request, form: Any) -> bool:
        cookie, field = request.cookies.get(CSRF_COOKIE, ""), str(form.get("csrf", ""))
        if not cookie or not field or not hmac.compare_digest(cookie, field):
            return False
        origin = request.headers.get("Origin")
        return origin is None or origin == f"{request.scheme}://{request.host}"


_APP = web.AppKey("robid", _App)
#: what the store and the views say of a thing that is not there (answered 404)
_MISSING = ("not in the store", "no identification stored", "no stored identification")


def _limit(request: web.Request) -> int:
    text = request.query.get("limit", str(views.RUNS_LIMIT))
    if not text.isdigit():
        raise web.HTTPBadRequest(text=f"limit: expected a whole number, got {text!r}\n")
    return int(text)


def _html(text: str) -> web.Response:
    return web.Response(text=text, content_type="text/html", charset="utf-8")


def _wants_json(request: web.Request) -> bool:
    return "application/json" in request.headers.get("Accept", "") or \
        request.headers.get("Authorization", "").startswith("Bearer ")


def _answer(request: web.Request, status: int, doc: dict[str, Any]) -> web.Response:
    if _wants_json(request):
        return web.json_response(doc, status=status)
    return web.Response(status=status, text=pages.message_page(doc), content_type="text/html",
                        charset="utf-8")


def _refuse(request: web.Request, why: str) -> web.Response:
    log.warning("web action refused from %s: %s", request.remote, why)
    return _answer(request, 403, {"ok": False, "error": f"forbidden: {why}"})


@web.middleware
async def _guard(request: web.Request, handler: Any) -> web.StreamResponse:
    """A foreign Host refused; security headers; the CSRF cookie on every page; store
    errors as one line."""
    app = request.app[_APP]
    if not app.hosts.allows(request.host):
        log.warning("web request refused from %s: Host %.80r", request.remote, request.host)
        resp = web.Response(status=421, text=f"Host {request.host[:80]!r} is not a name of "
                            f"this page ({app.hosts.shown}; other names go in web.hosts)\n")
        resp.headers.update(_HEADERS)
        return resp
    csrf = request.cookies.get(CSRF_COOKIE) or secrets.token_urlsafe(24)
    _CSRF.set(csrf)
    try:
        resp = await handler(request)
    except web.HTTPException as exc:  # answered as a response: it gets the headers too
        resp = web.Response(status=exc.status, text=exc.text, content_type="text/plain")
    except RobidError as err:
        missing = any(m in str(err) for m in _MISSING)
        resp = web.Response(status=404 if missing else 400, text=f"{err}\n")
    resp.headers.update(_HEADERS)
    if CSRF_COOKIE not in request.cookies and request.method == "GET":
        resp.set_cookie(CSRF_COOKIE, csrf, httponly=True, samesite="Strict",
                        secure=app.tls, path="/")
    return resp


def make_app(cfg: DaemonConfig, robot: str, *, actions: Actions | None = None,
             token: str | None = None, tls: bool = False, listen_host: str | None = None
             ) -> web.Application:
    """The page's aiohttp application (``actions``: the daemon's request handler, or None
    for a read-only page); requests must name ``listen_host`` (None: loopback only), a
    loopback name or one of ``web.hosts`` in their Host header."""
    app = web.Application(middlewares=[_guard], client_max_size=1 << 16)
    h = _App(cfg, robot, actions, token, tls, _Hosts(listen_host, cfg.web.hosts))
    app[_APP] = h
    app.add_routes([web.get("/", h.runs), web.get("/api/runs", h.runs),
                    web.get("/runs/{run_id}", h.run), web.get("/api/runs/{run_id}", h.run),
                    web.get("/compare", h.compare), web.get("/api/compare", h.compare),
                    web.get("/trend", h.trend), web.get("/api/trend", h.trend),
                    web.get("/params", h.params), web.get("/api/params", h.params),
                    web.get("/fleet", h.fleet), web.get("/api/fleet", h.fleet),
                    web.post("/actions/{action}", h.act)])
    return app


class WebServer:
    """``async with WebServer(cfg, listen, robot, actions=…)``: serve the page until exit.
    Refuses before binding a non-loopback address without TLS and a token."""

    def __init__(self, cfg: DaemonConfig, listen: str, robot: str, *,
                 actions: Actions | None = None, create_token: bool = False) -> None:
        self.host, self.port = parse_listen(listen)
        token = load_token(cfg.web, cfg.state_dir, create=create_token)
        if not _loopback(self.host):
            missing = [k for k in ("tls_cert", "tls_key") if getattr(cfg.web, k) is None]
            missing += [] if token else ["token"]
            if missing:
                raise ConfigError(f"web.listen: {listen} is not a loopback address; serving it "
                                  f"needs TLS and a token (missing: {', '.join(missing)})")
        self.ssl = _tls(cfg.web)
        self.app = make_app(cfg, robot, actions=actions, token=token, tls=self.ssl is not None,
                            listen_host=self.host)
        self._runner: web.AppRunner | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'https' if self.ssl else 'http'}://{host}:{self.port}/"

    async def __aenter__(self) -> WebServer:
        self._runner = web.AppRunner(self.app, access_log=None, handle_signals=False)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port, ssl_context=self.ssl)
        try:
            await site.start()
        except OSError as err:
            await self._runner.cleanup()
            raise ConfigError(f"web.listen: cannot listen on {self.host}:{self.port} "
                              f"({err.strerror})") from err
        if self.port == 0:  # the port the system chose (tests)
            self.port = int(self._runner.addresses[0][1])
        log.info("web page at %s", self.url)
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
