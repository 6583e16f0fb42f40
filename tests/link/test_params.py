"""Parameter sets through the daemon: each identification's set is kept; an unattended run
uploads only an approved set; a rollback gives the controller its previous set byte for byte;
a set the controller never acknowledges leaves it with the one it had."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from robid_link.config import load_daemon_config
from robid_link.exceptions import ConfigError
from robid_link.link.daemon import Daemon

from .conftest import QUICK, wait_run, write_config

ONE = {**QUICK, "experiments": QUICK["experiments"][:1], "upload": True}


async def _run(d: Daemon, trigger: str = "operator") -> dict[str, Any]:
    ans = await d.handle({"cmd": "start", "campaign": "cal", "trigger": trigger})
    return await wait_run(d, ans["run_id"])


def _daemon(cfg: Path, body: Any) -> Any:
    async def go() -> Any:
        async with asyncio.timeout(300), Daemon(load_daemon_config(cfg), env={}) as d:
            return await body(d)

    return asyncio.run(go())


def test_sets_approval_rollback(tmp_path: Path, controller: Any) -> None:
    cfg = write_config(tmp_path, {"cal": ONE})

    async def body(d: Daemon) -> dict[str, Any]:
        assert d.store is not None
        first = await _run(d)
        second = await _run(d)
        sets = await d.store.param_sets("arm3")
        in_use_before = ctrl.core.feedforward.sha256
        with pytest.raises(ConfigError, match="no parameter set matches 'zz'"):
            await d.handle({"cmd": "params_approve", "robot": "arm3", "set": "zz"})
        back = await d.handle({"cmd": "params_rollback", "robot": "arm3"})
        in_use_after = ctrl.core.feedforward.sha256
        await d.handle({"cmd": "approve", "campaign": "cal"})  # programs, for the timer run
        night = await _run(d, "timer")
        return {"runs": (first, second, night), "sets": sets, "before": in_use_before,
                "after": in_use_after, "back": back,
                "uploads": await d.store.uploads("arm3"),
                "final": ctrl.core.feedforward.sha256,
                "all_sets": await d.store.param_sets("arm3")}

    with controller() as ctrl:
        out = _daemon(cfg, body)
    first, second, night = out["runs"]
    assert first["state"] == second["state"] == "completed"
    v1, v2 = out["sets"]
    assert out["before"] == v2["sha256"] and out["after"] == v1["sha256"]
    assert "rolled arm3 back to parameter set 1" in out["back"]["message"]
    # byte for byte: the file the controller loaded on rollback is set 1's stored bytes
    files = sorted((tmp_path / "share" / "params").glob("params-arm3.*.json"),
                   key=lambda f: f.stat().st_mtime_ns)
    assert len(files) == 3 and files[-1].read_bytes() == v1["body"] == files[0].read_bytes()
    # the unattended run identified a third set, not approved: refused, nothing uploaded
    assert night["state"] == "failed"
    assert "unattended upload refused: parameter set 3 of arm3" in night["error"]
    assert out["final"] == v1["sha256"]
    states = [u["state"] for u in out["uploads"]]
    assert states == ["sent", "acknowledged"] * 3  # two uploads and the rollback; none at night


def test_an_unacknowledged_set_leaves_the_old_one(tmp_path: Path, controller: Any) -> None:
    cfg = write_config(tmp_path, {"cal": ONE})

    async def body(d: Daemon) -> dict[str, Any]:
        assert d.store is not None
        run = await _run(d)
        return {"run": run, "uploads": await d.store.uploads("arm3")}

    with controller(fault="no_param_ack") as ctrl:
        from robid_link.link import campaign

        real = campaign.upload_set

        async def short(*a: Any, **kw: Any) -> None:
            await real(*a, **{**kw, "timeout_s": 1.0})

        campaign.upload_set = short  # type: ignore[assignment]
        try:
            out = _daemon(cfg, body)
        finally:
            campaign.upload_set = real  # type: ignore[assignment]
    assert out["run"]["state"] == "failed"
    assert "did not acknowledge parameter set" in out["run"]["error"]
    assert "keeps its previous set" in out["run"]["error"]
    assert ctrl.core.feedforward is None
    assert [u["state"] for u in out["uploads"]] == ["sent", "failed"]


def test_another_robots_sets_are_refused_naming_both(tmp_path: Path, controller: Any) -> None:
    """A daemon of robot cell-a on a store shared with cell-b: approving cell-b's set was a
    silent no-op answered 'approved', and a rollback sent cell-b's set to cell-a's
    controller; both refused in one line naming both robots, before anything changes."""
    import hashlib

    from robid_link.link.store import Store

    bodies = [b'{"x": 1}', b'{"x": 2}']
    with Store(tmp_path / "state", robot="cell-b") as b:
        run_b = b.create_run("cal", "operator", {}, [])
        for body in bodies:
            sha = hashlib.sha256(body).hexdigest()
            b.add_param_set({"sha256": sha, "robot": "cell-b", "run_id": run_b}, body)
            b.record_upload("cell-b", sha, run_b, "acknowledged")
    cfg = write_config(tmp_path, {"cal": ONE}, robot_name="cell-a")

    async def refused(d: Daemon) -> list[str]:
        errors = []
        for cmd in ("params_approve", "params_rollback"):
            with pytest.raises(ConfigError) as err:
                await d.handle({"cmd": cmd, "robot": "cell-b", "set": "1"})
            errors.append(str(err.value))
        return errors

    with controller() as ctrl:
        approve, rollback = _daemon(cfg, refused)
    assert approve == ("robot cell-b: this daemon holds robot cell-a; approve cell-b's "
                       "parameter sets with cell-b's own daemon")
    assert rollback == ("robot cell-b: this daemon holds robot cell-a; roll back cell-b's "
                        "parameter sets with cell-b's own daemon")
    assert ctrl.core.feedforward is None  # nothing reached cell-a's controller
    with Store(tmp_path / "state", robot="cell-b", readonly=True) as b:
        assert [s["approved"] for s in b.param_sets("cell-b")] == [None, None]
        assert len(b.uploads("cell-b")) == 2
