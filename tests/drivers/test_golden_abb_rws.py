"""The RWS transcripts (``tests/golden/abb_rws/rws1.yaml``, ``rws2.yaml``, written from ABB's
Robot Web Services manuals) against both sides: the driver sends exactly the transcript's
requests — method, path, query, media types, form fields, bodies — for one cycle and a
parameter upload (recorded at a recording fake controller); the fake controller, sent the
transcript's requests by a plain aiohttp client, answers each as the transcript says, events
on the websocket included."""

from __future__ import annotations

import asyncio
import base64
import json
import re
import ssl
import threading
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlencode

import aiohttp
import pytest
from yarl import URL

from robid_link.fakes.rws.peer import RwsPeer
from robid_link.ident.model.robot import Robot
from robid_link.jobs import RobotInfo
from robid_link.link import registry
from tests.drivers import golden

VERSIONS = [pytest.param(1, id="rws1"), pytest.param(2, id="rws2")]
#: a module the controller loads (RAPID reference: MODULE, CONST jointtarget, PROC, MoveAbsJ)
MODULE = b"""MODULE robid_path
    CONST jointtarget path{1} := [[[0,0,0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]]];
    PROC robid_move()
        MoveAbsJ path{1}, v100, fine, tool0;
    ENDPROC
ENDMODULE
"""


def _names(doc: dict[str, Any], peer: RwsPeer) -> dict[str, Any]:
    return {**golden.common(), "nonce": doc["nonce"], "port": peer.port, "sid": "1"}


class _Recorder:
    """``RwsPeer.tap``: every request as it arrives (method, path, query, headers, body), its
    answer added when it is answered; opens ``gate`` once the daemon, subscribed, has read
    the execution state (the program may end only then: the transcript's order)."""

    def __init__(self, gate: threading.Event) -> None:
        self.requests: list[dict[str, Any]] = []
        self.gate = gate

    def __call__(self, what: str, request: Any, data: Any) -> None:
        if what == "request":
            auth = request.headers.get("Authorization", "")
            self.requests.append({
                "id": id(request), "method": request.method, "path": request.path,
                "query": dict(request.query), "accept": request.headers.get("Accept"),
                "content_type": request.headers.get("Content-Type"), "body": data,
                "authorization": auth.split(" ")[0] or None,
                "websocket": request.headers.get("Sec-WebSocket-Protocol")})
            return
        # the latest unanswered entry of this (live) request object: ids are reused later
        entry = next(r for r in reversed(self.requests) if r["id"] == id(request)
                     and "status" not in r)
        entry["status"] = data.status
        subscribed = any(r["path"].startswith("/poll/") for r in self.requests)
        if request.path == "/rw/rapid/execution" and request.method == "GET" and subscribed:
            self.gate.set()


def _check_request(spec: dict[str, Any], rec: dict[str, Any], doc: dict[str, Any],
                   names: dict[str, Any]) -> None:
    spec = golden.fill(spec, names)
    where = f"{spec['method']} {spec['path']}"
    assert (rec["method"], rec["path"]) == (spec["method"], spec["path"])
    assert rec["query"] == spec.get("query", {}), where
    if "authorization" in spec:
        assert rec["authorization"] == spec["authorization"], where
    if doc["accept"] and spec["path"].startswith(("/rw", "/subscription")) and (
            spec["method"] != "DELETE"):
        assert rec["accept"] == doc["accept"], where
    if "form" in spec:
        assert rec["content_type"] == doc["form_type"], where
        assert parse_qsl(rec["body"].decode(), keep_blank_values=True) == [
            tuple(pair) for pair in spec["form"]], where
    elif "body" in spec or "rapid_module" in spec:
        if doc["upload_type"]:
            assert rec["content_type"] == doc["upload_type"], where
        if "body" in spec:
            assert rec["body"] == spec["body"], where
        else:
            text = rec["body"].decode()
            assert text.splitlines()[0] == f"MODULE {spec['rapid_module']}", where
            assert "PROC robid_move()" in text, where
    elif "websocket" in spec:
        assert rec["websocket"] == spec["websocket"], where
    else:
        assert rec["body"] == b"", where


@pytest.mark.parametrize("version", VERSIONS)
def test_driver_sends_the_transcript(tmp_path: Path, robot: Robot, version: int) -> None:
    doc = golden.load("abb_rws", f"rws{version}.yaml")
    gate = threading.Event()
    core = golden.ScriptedCore(robot, golden.common()["log_csv"], gate)
    peer = RwsPeer(core, tmp_path, version=version)
    peer.tap = recorder = _Recorder(gate)

    async def cycle(names: dict[str, Any]) -> None:
        driver = registry.make_driver(peer.driver_options())
        driver.bind_robot(RobotInfo.of(robot))
        async with driver:
            await driver.put_program(golden.program(names))
            await driver.give_ready("exp1", doc["nonce"])
            done = await driver.take_done("exp1", doc["nonce"], timeout_s=20)
            assert await driver.fetch_logs(done) == names["log_csv"]
            await driver.acknowledge(done)
            await driver.upload_parameters(json.loads(names["params"]),
                                           timeout_s=20)

    with peer:
        names = _names(doc, peer)
        asyncio.run(cycle(names))
    exchanges = [ex for ex in doc["exchanges"] if "request" in ex]
    assert [(r["method"], r["path"]) for r in recorder.requests] == [
        (ex["request"]["method"], golden.fill(ex["request"]["path"], names))
        for ex in exchanges]
    for ex, rec in zip(exchanges, recorder.requests, strict=True):
        _check_request(ex["request"], rec, doc, names)
        assert rec.get("status", 101) == ex["response"]["status"], rec["path"]
    assert core.loaded == [names["params"]]


class _Client:
    """A plain RWS client on aiohttp: the transcript's requests, sent as written."""

    def __init__(self, peer: RwsPeer, doc: dict[str, Any]) -> None:
        self.doc, self.version = doc, peer.version
        self.base = URL(f"{'https' if peer.tls else 'http'}://127.0.0.1:{peer.port}")
        self.ssl: Any = (ssl.create_default_context(cafile=peer.workdir / "rws-cert.pem")
                         if peer.tls else True)
        user, _, password = peer.credentials.read_text().strip().partition(":")
        if self.version == 1:
            self.session = aiohttp.ClientSession(
                cookie_jar=aiohttp.CookieJar(unsafe=True),
                middlewares=(aiohttp.DigestAuthMiddleware(user, password),))
        else:
            token = base64.b64encode(f"{user}:{password}".encode()).decode()
            self.session = aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True),
                                                 headers={"Authorization": f"Basic {token}"})
        self.ws: aiohttp.ClientWebSocketResponse | None = None

    async def send(self, spec: dict[str, Any], auth: bool = True
                   ) -> tuple[int, dict[str, str], bytes]:
        headers, data = {}, None
        if self.doc["accept"] and spec["path"].startswith(("/rw", "/subscription")):
            headers["Accept"] = self.doc["accept"]
        if "form" in spec:
            headers["Content-Type"] = self.doc["form_type"]
            data = urlencode([tuple(p) for p in spec["form"]]).encode()
        elif "body" in spec or "rapid_module" in spec:
            if self.doc["upload_type"]:
                headers["Content-Type"] = self.doc["upload_type"]
            data = spec["body"] if "body" in spec else MODULE
        url = self.base.with_path(spec["path"], encoded=True).with_query(spec.get("query", {}))
        if not auth:
            async with aiohttp.request(spec["method"], url, ssl=self.ssl) as resp:
                return resp.status, dict(resp.headers), await resp.read()
        async with self.session.request(spec["method"], url, data=data, headers=headers,
                                        ssl=self.ssl, allow_redirects=False) as resp:
            return resp.status, dict(resp.headers), await resp.read()

    async def subscribe(self, spec: dict[str, Any]) -> None:
        url = self.base.with_scheme("wss" if self.base.scheme == "https" else "ws").with_path(
            spec["path"])
        self.ws = await self.session.ws_connect(url, protocols=(spec["websocket"],),
                                                ssl=self.ssl)
        assert self.ws.protocol == spec["websocket"]

    async def event(self) -> str:
        assert self.ws is not None
        async with asyncio.timeout(10):
            msg = await self.ws.receive()
        assert msg.type == aiohttp.WSMsgType.TEXT, msg
        return str(msg.data)

    async def close(self) -> None:
        if self.ws is not None:
            await self.ws.close()
        await self.session.close()


async def _replay(peer: RwsPeer, doc: dict[str, Any], names: dict[str, Any],
                  gate: threading.Event) -> None:
    client = _Client(peer, doc)
    try:
        for ex in doc["exchanges"]:
            if "event" in ex:
                assert await client.event() == golden.fill(ex["event"], names)
                continue
            spec, want = golden.fill(ex["request"], names), ex["response"]
            if "websocket" in spec:
                await client.subscribe(spec)
                continue
            status, headers, body = await client.send(spec, auth=want["status"] != 401)
            assert status == want["status"], (spec["path"], body[:200])
            if "authenticate" in want:
                assert headers["WWW-Authenticate"].startswith(want["authenticate"])
            if "location" in want:
                names["sid"] = re.sub(r".*/poll/", "", headers["Location"])
                assert headers["Location"] == golden.fill(want["location"], names)
            if "json" in want:
                got = json.loads(body)
                got.pop("_links", None)
                assert got == golden.fill(want["json"], names), spec["path"]
                if "running" in str(want["json"]):
                    gate.set()  # the program ends now
            if "body" in want:
                assert body == golden.fill(want["body"], names)
    finally:
        await client.close()


@pytest.mark.parametrize("version", VERSIONS)
def test_peer_answers_the_transcript(tmp_path: Path, robot: Robot, version: int) -> None:
    doc = golden.load("abb_rws", f"rws{version}.yaml")
    gate = threading.Event()
    core = golden.ScriptedCore(robot, golden.common()["log_csv"], gate)
    with RwsPeer(core, tmp_path, version=version) as peer:
        names = _names(doc, peer)
        asyncio.run(_replay(peer, doc, names, gate))
    assert core.runs == [("exp1", doc["nonce"], names["traj_csv"], names["traj_yaml"])]
    assert core.loaded == [names["params"]]


def test_a_long_robot_name_fits_a_rapid_string(tmp_path: Path, robot: Robot) -> None:
    """``robid_params`` holds the set's path: a RAPID string, at most 80 characters (the fake
    controller refuses a longer one, as RAPID does)."""
    core = golden.ScriptedCore(robot, b"")
    doc = {"format": "robid-parameter-set/1", "robot": "r" * 60, "theta": [1.0]}
    with RwsPeer(core, tmp_path, version=1) as peer:
        async def upload() -> None:
            driver = registry.make_driver(peer.driver_options())
            driver.bind_robot(RobotInfo.of(robot))
            async with driver:
                await driver.upload_parameters(doc, timeout_s=10)

        asyncio.run(upload())
    assert len(peer.vars["robid_params"]) == 80 and len(core.loaded) == 1
