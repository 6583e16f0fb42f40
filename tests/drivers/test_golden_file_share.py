"""The file-share transcript (``tests/golden/file_share/cycle.yaml``, from
docs/file_share_protocol.md) against both sides: the driver writes and deletes exactly its
files, in order, with their contents; the fake controller answers exactly the transcript's."""

from __future__ import annotations

import asyncio
import json
import os
import re
import time
from pathlib import Path
from typing import Any

import pytest

from robid_link.drivers.file_share import FileShareDriver
from robid_link.fakes.file_share_peer import FileSharePeer
from robid_link.ident.model.robot import Robot
from tests.drivers import golden

ANY_NUMBER = object()


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file of the share by its path, without temporary (dot) files."""
    out = {}
    for folder, _, files in os.walk(root):
        for name in files:
            rel = Path(folder, name).relative_to(root)
            if not any(part.startswith(".") for part in rel.parts):
                out[rel.as_posix()] = Path(folder, name).read_bytes()
    return out


def _diff(before: dict[str, bytes], after: dict[str, bytes]) -> tuple[dict[str, bytes],
                                                                      list[str]]:
    written = {k: v for k, v in after.items() if before.get(k) != v}
    return written, sorted(k for k in before if k not in after)


def _same(spec: Any, got: Any) -> bool:
    if spec is ANY_NUMBER:
        return isinstance(got, int | float) and not isinstance(got, bool)
    if isinstance(spec, dict):
        return isinstance(got, dict) and spec.keys() == got.keys() and all(
            _same(spec[k], got[k]) for k in spec)
    return bool(spec == got)


def _content_ok(spec: Any, data: bytes) -> bool:
    if isinstance(spec, dict) and "json" in spec:
        text = data.decode()
        return text.endswith("\n") and text.count("\n") == 1 and _same(spec["json"],
                                                                       json.loads(text))
    if isinstance(spec, dict) and "rapid_module" in spec:
        return data.decode().splitlines()[0] == f"MODULE {spec['rapid_module']}"
    return data == (spec.encode() if isinstance(spec, str) else spec)


def _check_writes(step: dict[str, Any], written: dict[str, bytes], names: dict[str, Any]
                  ) -> None:
    want = golden.fill(step.get("write", {}), names)
    assert sorted(written) == sorted(want), f"step {step['step']}: files written"
    for path, spec in want.items():
        assert _content_ok(spec, written[path]), f"step {step['step']}: {path}: {written[path]!r}"


def _names(doc: dict[str, Any]) -> dict[str, Any]:
    return {**golden.common(), "nonce": doc["nonce"], "number": ANY_NUMBER}


def _pnonce(root: Path, doc: dict[str, Any], names: dict[str, Any]) -> None:
    """The parameter set's nonce as found on the share, checked against its pattern."""
    found = [p.name for p in (root / "params").iterdir() if not p.name.startswith(".")]
    assert len(found) == 1, found
    m = re.fullmatch(rf"params-arm3\.({doc['pnonce']})\.json", found[0])
    assert m, found[0]
    names["pnonce"] = m.group(1)


def _record(monkeypatch: pytest.MonkeyPatch, share: Path) -> list[tuple[str, str]]:
    """Every file the driver puts in place (a rename onto its name) or deletes, in order."""
    ops: list[tuple[str, str]] = []
    replace, unlink = os.replace, Path.unlink

    def put_in_place(src: Any, dst: Any, *args: Any, **kw: Any) -> None:
        replace(src, dst, *args, **kw)
        if Path(dst).is_relative_to(share):
            ops.append(("write", Path(dst).relative_to(share).as_posix()))

    def delete(path: Path, missing_ok: bool = False) -> None:
        existed = path.exists()
        unlink(path, missing_ok=missing_ok)
        if existed and path.is_relative_to(share):
            ops.append(("delete", path.relative_to(share).as_posix()))

    monkeypatch.setattr(os, "replace", put_in_place)
    monkeypatch.setattr(Path, "unlink", delete)
    return ops


def _ops(step: dict[str, Any], names: dict[str, Any]) -> list[tuple[str, str]]:
    return ([("write", p) for p in golden.fill(step.get("write", {}), names)]
            + [("delete", p) for p in golden.fill(step.get("delete", []), names)])


def test_driver_writes_the_transcript(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    doc = golden.load("file_share", "cycle.yaml")
    names, steps = _names(doc), {s["step"]: s for s in doc["steps"][:6]}
    upload, load, ack = doc["steps"][6:]
    nonce, share = doc["nonce"], tmp_path / "share"
    share.mkdir()
    ops = _record(monkeypatch, share)

    async def controller() -> None:
        """Answers the parameter set's ready as the transcript's controller does."""
        before = _snapshot(share)
        while not any(n.endswith(".ready") for n in os.listdir(share / "sem")):
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)  # both the set and its ready are written
        written, deleted = _diff(before, _snapshot(share))
        _pnonce(share, doc, names)
        _check_writes(upload, written, names)
        assert deleted == [] and ops == _ops(upload, names)
        for path, data in golden.fill(load["write"], names).items():
            (share / path).write_text(data)

    async def cycle() -> None:
        driver = FileShareDriver(share=share, canary_interval_s=0)
        async with driver:
            snap = _snapshot(share)

            def step(name: str) -> None:
                nonlocal snap
                new = _snapshot(share)
                _check_writes(steps[name], _diff(snap, new)[0], names)
                assert ops == _ops(steps[name], names), name
                snap = new
                ops.clear()

            await driver.put_program(golden.program(names))
            step("put")
            await driver.give_ready("exp1", nonce)
            await driver.give_ready("exp1", nonce)  # given again: nothing new
            step("give")
            for path, data in golden.fill(steps["answer"]["write"], names).items():
                (share / path).write_bytes(data if isinstance(data, bytes) else data.encode())
            snap = _snapshot(share)
            ops.clear()
            done = await driver.take_done("exp1", nonce, timeout_s=10)
            step("take")
            assert await driver.fetch_logs(done) == names["log_csv"]
            step("fetch")
            await driver.acknowledge(done)
            step("acknowledge")
            answering = asyncio.create_task(controller())
            await driver.upload_parameters(json.loads(names["params"]), timeout_s=10)
            await answering
            assert ops == _ops(upload, names) + _ops(ack, names)

    asyncio.run(cycle())


def _wait_for(root: Path, paths: list[str], timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while not all((root / p).exists() for p in paths):
        assert time.monotonic() < end, f"controller never wrote {paths}"
        time.sleep(0.01)


def test_peer_answers_the_transcript(tmp_path: Path, robot: Robot) -> None:
    doc = golden.load("file_share", "cycle.yaml")
    names = _names(doc)
    put, give, answer, _, _, ack, _, load, ack2 = doc["steps"]
    core = golden.ScriptedCore(robot, names["log_csv"])
    share = tmp_path / "share"
    names["pnonce"] = "41373bf26405beef"
    with FileSharePeer(core, share, poll_s=0.005):
        (share / "sem" / ".canary.1.1").write_bytes(b"")  # not a semaphore: ignored
        ready = {"experiment": "exp1", "nonce": doc["nonce"], "time": time.time()}
        for step in (put, give):
            for path, spec in golden.fill(step["write"], names).items():
                if isinstance(spec, dict):  # the ready's JSON, or the RAPID module
                    spec = (json.dumps(ready) + "\n").encode() if "json" in spec else (
                        b"MODULE robid_exp1\nENDMODULE\n")
                (share / path).write_bytes(spec)
        want = golden.fill(answer["write"], names)
        before = _snapshot(share)
        _wait_for(share, list(want))
        time.sleep(0.05)
        _check_writes(answer, _diff(before, _snapshot(share))[0], names)
        assert core.runs == [("exp1", doc["nonce"], names["traj_csv"], names["traj_yaml"])]
        for path in golden.fill(ack["delete"], names):
            (share / path).unlink()
        (share / "params").mkdir()
        (share / golden.fill("params/params-arm3.<<pnonce>>.json", names)).write_bytes(
            names["params"])
        ready = {"experiment": "params-arm3", "nonce": names["pnonce"], "time": time.time()}
        (share / golden.fill("sem/params-arm3.<<pnonce>>.ready", names)).write_text(
            json.dumps(ready) + "\n")
        before = _snapshot(share)
        _wait_for(share, list(golden.fill(load["write"], names)))
        time.sleep(0.05)
        _check_writes(load, _diff(before, _snapshot(share))[0], names)
        assert core.loaded == [names["params"]] and len(core.runs) == 1
        assert sorted(golden.fill(ack2["delete"], names)) == sorted(
            p for p in _snapshot(share) if p.startswith("sem/params-"))

