"""The daemon in-process against the fake controller thread: campaigns, every fault mode of the
controller (a clear error or a bounded retry, no captured log lost), approvals for unattended
runs, unsafe programs refused before they reach the share, the control socket."""

from __future__ import annotations

import asyncio
import json
import os
import re
import stat
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from robid_link.config import load_daemon_config
from robid_link.exceptions import ApprovalError, ConfigError, UnsafeProgramError
from robid_link.jobs import MotionProgram
from robid_link.link.control import request
from robid_link.link.daemon import Daemon
from robid_link.link.driver import CAP_FEEDFORWARD, Done, Driver

from .conftest import QUICK, wait_run, write_config

ONE = {"experiments": [QUICK["experiments"][0]], "identify": False, "timeout_s": 4,
       "backoff_s": 0.05, "retries": 2}


def with_daemon(cfg_path: Path, body: Callable[[Daemon], Awaitable[Any]],
                env: dict[str, str] | None = None) -> Any:
    async def go() -> Any:
        async with asyncio.timeout(120), Daemon(load_daemon_config(cfg_path), env=env or {}) as d:
            return await body(d)

    return asyncio.run(go())


async def start(daemon: Daemon, campaign: str = "one", trigger: str = "operator") -> dict:
    ans = await daemon.handle({"cmd": "start", "campaign": campaign, "trigger": trigger})
    return await wait_run(daemon, ans["run_id"])


def test_campaign_runs_to_completion(tmp_path: Path, controller: Any) -> None:
    cfg = write_config(tmp_path, {"quick": {**QUICK, "diagnose": True, "upload": True}})

    async def body(d: Daemon) -> tuple[dict, list]:
        run = await start(d, "quick")
        return run, await d.store.results(run_id=run["run_id"])  # type: ignore[union-attr]

    with controller() as ctrl:
        run, results = with_daemon(cfg, body)
    assert run["state"] == "completed", run["error"]
    assert [e["state"] for e in run["experiments"]] == ["stored", "stored"]
    assert len(ctrl.handled) == 2
    kinds = {r["kind"]: r["record"] for r in results}
    assert set(kinds) == {"identify", "diagnose"}
    rec = kinds["identify"]
    assert rec["robot"] == "arm3" and len(rec["rmse"]) == 3
    assert {d["sha256"] for d in rec["data"]} == {e["log_sha"] for e in run["experiments"]}
    report = tmp_path / "state" / "reports" / run["run_id"]
    assert (report / "summary.txt").is_file() and (report / "identify.json").is_file()
    uploaded = list((tmp_path / "share" / "params").glob("params-arm3.*.json"))  # upload
    assert len(uploaded) == 1
    params = json.loads(uploaded[0].read_text())
    assert params["run_id"] == run["run_id"] and params["robot"] == "arm3"
    identified = json.loads((report / "identify.json").read_text())["parameters"]
    # the controller's set: the physically consistent fit of the same logs and model
    assert params["physically_consistent"] is True and len(identified) > 0
    names = {p["name"] for p in params["base_parameters"]}
    assert {"m_1", "zz_3", "fv_1", "fc_3"} <= names
    assert ctrl.core.feedforward.sha256 == params["sha256"]  # the controller loaded it


def test_a_campaign_keeps_its_logs_in_the_log_store_folder(tmp_path: Path,
                                                           controller: Any) -> None:
    """``log_store: FOLDER`` (a plant's central log folder): the cycle finds the log it
    stored there, the run completes, nothing is written under the state dir's logs."""
    central = tmp_path / "central"
    cfg = write_config(tmp_path, {"one": ONE}, log_store=str(central))

    async def body(d: Daemon) -> dict:
        return await start(d)

    with controller() as ctrl:
        run = with_daemon(cfg, body)
    assert run["state"] == "completed", run["error"]
    assert len(ctrl.handled) == 1
    sha = run["experiments"][0]["log_sha"]
    assert [p.name for p in central.rglob("*.csv")] == [f"{sha}.csv"]
    assert list((tmp_path / "state" / "logs").rglob("*.csv")) == []


@pytest.mark.parametrize("fault, journal_error", [
    ("never_answer", "no 'done' for experiment rigid_body"),
    ("truncated_log", "truncated log"),
    ("corrupt_log", "fails its checksum"),
    ("nan_log", "log of experiment rigid_body (kept as "),
    ("fail", "controller reports experiment rigid_body failed"),
])
def test_faults_are_retried_and_lose_nothing(tmp_path: Path, controller: Any, fault: str,
                                             journal_error: str) -> None:
    cfg = write_config(tmp_path, {"one": ONE})

    async def body(d: Daemon) -> tuple[dict, list, int]:
        run = await start(d)
        store = d.store
        assert store is not None
        return run, await store.journal(run["run_id"]), await store.log_count()

    with controller(fault=fault) as ctrl:
        run, journal, n_logs = with_daemon(cfg, body)
    assert run["state"] == "completed", run["error"]
    failed = [j for j in journal if j["step"] == "attempt_failed"]  # retried: not final
    assert len(failed) == 1 and journal_error in failed[0]["detail"]["error"]
    assert "\n" not in failed[0]["detail"]["error"]
    assert [j["step"] for j in journal].count("retry") == 1
    assert run["experiments"][0]["attempt"] == 2 and len(ctrl.handled) == 2
    # a log the controller delivered intact is kept even when it was rejected
    assert n_logs == (2 if fault == "nan_log" else 1)
    share = tmp_path / "share" / "sem"
    assert not any(n.endswith(".ready") for n in os.listdir(share))  # withdrawn or acknowledged


@pytest.mark.parametrize("fault", ["answer_twice", "stale_semaphore"])
def test_duplicate_and_stale_answers_are_ignored(tmp_path: Path, controller: Any, fault: str,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    cfg = write_config(tmp_path, {"one": ONE})

    async def body(d: Daemon) -> dict:
        run = await start(d)
        await asyncio.sleep(0.2)
        return run

    with caplog.at_level("WARNING", logger="robid"), controller(fault=fault):
        run = with_daemon(cfg, body)
    assert run["state"] == "completed" and run["experiments"][0]["attempt"] == 1
    assert ("duplicate_semaphore" if fault == "answer_twice" else "stale_semaphore") in caplog.text


def test_controller_dies_mid_program_then_comes_back(tmp_path: Path, controller: Any) -> None:
    cfg = write_config(tmp_path, {"one": {**ONE, "timeout_s": 2}})

    async def body(d: Daemon) -> dict:
        ans = await d.handle({"cmd": "start", "campaign": "one"})
        first = controller(fault="die")
        with first as ctrl:
            while not ctrl.handled and first.thread.is_alive():
                await asyncio.sleep(0.02)
            await asyncio.to_thread(first.thread.join, 10)
        assert not first.thread.is_alive()  # the controller is dead, the daemon waits
        while not any(j["step"] == "attempt_failed"
                      for j in await d.store.journal(ans["run_id"])):  # type: ignore
            await asyncio.sleep(0.05)  # the take times out; the attempt is withdrawn
        with controller():  # restarted controller; the daemon's retry reaches it
            return await wait_run(d, ans["run_id"])

    run = with_daemon(cfg, body)
    assert run["state"] == "completed" and run["experiments"][0]["attempt"] == 2
    partial = [n for n in os.listdir(tmp_path / "share" / "outbox") if n.endswith(".partial")]
    assert partial  # the dead controller's half log is never taken for a log


def test_bounded_retries_end_in_a_clear_failure(tmp_path: Path, controller: Any) -> None:
    cfg = write_config(tmp_path, {"one": {**ONE, "retries": 1}})

    async def body(d: Daemon) -> tuple[dict, int]:
        run = await start(d)
        return run, await d.store.log_count()  # type: ignore[union-attr]

    with controller(fault="corrupt_log", fault_count=10) as ctrl:
        run, n_logs = with_daemon(cfg, body)
    assert run["state"] == "failed"
    assert run["error"].startswith("experiment rigid_body: ")
    assert "after 2 attempts" in run["error"] and len(ctrl.handled) == 2
    assert n_logs == 0  # nothing corrupt was stored as a log


def test_unsafe_program_never_reaches_the_share(tmp_path: Path, controller: Any) -> None:
    from robid_link.ident.excite import excitation as ex
    from robid_link.ident.model.robot import load_robot

    from .conftest import ARM3

    robot = load_robot(ARM3)
    t = ex.np.arange(0.0, 2.0, 0.01)
    q = ex.np.zeros((t.size, 3))
    q[:, 0] = 2.0 * ex.np.sin(2 * ex.np.pi * 2.0 * t)  # 2 rad at 2 Hz: far beyond 120 deg/s
    ex.write_trajectory(tmp_path / "wild.csv", ex.Trajectory(t, q, 100.0, "custom", "arm3"))
    cfg = write_config(tmp_path, {"wild": {"experiments": [
        {"kind": "custom", "id": "wild", "trajectory": str(tmp_path / "wild.csv")}],
        "identify": False}})

    async def body(d: Daemon) -> str:
        with pytest.raises(UnsafeProgramError) as info:  # refused at start: no run at all
            await start(d, "wild")
        assert await d.store.runs() == []  # type: ignore[union-attr]
        return str(info.value)

    with controller() as ctrl:
        error = with_daemon(cfg, body)
    run = {"error": error}
    assert run["error"].startswith("unsafe program refused: experiment wild: qd1 = ")
    assert os.listdir(tmp_path / "share" / "inbox") == [] and ctrl.handled == []
    # the refusal quotes the program's peak speed against the robot's own limit
    m = re.search(r"qd1 = ([\d.]+) deg/s at sample \d+ exceeds the limit ([\d.]+) deg/s",
                  run["error"])
    assert m is not None, run["error"]
    assert float(m[2]) == pytest.approx(float(ex.np.degrees(robot.limits.qd_max[0])), rel=1e-3)
    assert float(m[1]) > float(m[2])


def test_unattended_runs_need_approved_programs(tmp_path: Path, controller: Any) -> None:
    """A timer start with a program nobody approved is refused at once (nothing to do: no run
    queued, nothing given to the controller); approved, it runs."""
    cfg = write_config(tmp_path, {"one": ONE})

    async def body(d: Daemon) -> tuple[str, list[Any], dict, dict]:
        with pytest.raises(ApprovalError) as refused:
            await start(d, trigger="timer")
        runs = await d.store.runs()  # type: ignore[union-attr]
        approved = await d.handle({"cmd": "approve", "campaign": "one"})
        ran = await start(d, trigger="timer")
        return str(refused.value), runs, approved, ran

    with controller() as ctrl:
        refused, runs, approved, ran = with_daemon(cfg, body)
    assert refused.startswith("campaign one: nothing to do unattended: the program of "
                              "experiment rigid_body (")
    assert "robid campaign approve one" in refused and runs == []
    assert approved["approved"][0]["sha256"] == ran["experiments"][0]["program_sha"]
    assert ran["state"] == "completed" and len(ctrl.handled) == 1


def test_a_web_start_runs_only_approved_programs(tmp_path: Path, controller: Any) -> None:
    """The page may be far from the cell: its start is unattended. Before the programs are
    approved it is refused in one line and nothing is queued or given; once approved it runs,
    and after a restart it is still held to the approvals (its trigger is stored)."""
    from robid_link.exceptions import ApprovalError

    cfg = write_config(tmp_path, {"one": ONE})
    web = {"cmd": "start", "campaign": "one", "trigger": "web", "by": "web"}

    async def body(d: Daemon) -> tuple[str, int, dict]:
        assert d.store is not None
        with pytest.raises(ApprovalError) as err:
            await d.handle(web)
        runs = len(await d.store.runs())
        await d.handle({"cmd": "approve", "campaign": "one"})
        ans = await d.handle(web)
        return str(err.value), runs, await wait_run(d, ans["run_id"])

    with controller() as ctrl:
        refused, runs, ran = with_daemon(cfg, body)
    assert re.fullmatch(r"web start refused: the program of experiment rigid_body \(\w{12}\) is "
                        r"not approved; run: robid campaign approve one --config \S+", refused)
    assert runs == 0 and ctrl.handled[1:] == []
    assert ran["state"] == "completed" and ran["trigger"] == "web" and len(ctrl.handled) == 1


def test_reduced_speed_first_run(tmp_path: Path, controller: Any) -> None:
    cfg = write_config(tmp_path, {"one": {**ONE, "reduced_speed_first": 0.5}})

    async def body(d: Daemon) -> dict:
        return await start(d)

    with controller() as ctrl:
        run = with_daemon(cfg, body)
    assert run["state"] == "completed"
    assert [e["exp_id"] for e in run["experiments"]] == ["rigid_body-slow", "rigid_body"]
    assert [h[0] for h in ctrl.handled] == ["rigid_body-slow", "rigid_body"]


def test_control_socket_mode_stale_file_and_commands(tmp_path: Path, controller: Any) -> None:
    cfg = write_config(tmp_path, {"one": ONE})
    sock = tmp_path / "ctl.sock"
    import socket

    s = socket.socket(socket.AF_UNIX)  # a socket file left by a dead daemon
    s.bind(str(sock))
    s.close()

    async def body(d: Daemon) -> dict[str, Any]:
        out: dict[str, Any] = {"mode": stat.S_IMODE(os.stat(sock).st_mode)}
        ping = await asyncio.to_thread(request, sock, {"cmd": "ping"})
        out["pid"] = ping["pid"]
        listed = await asyncio.to_thread(request, sock, {"cmd": "list"})
        out["campaigns"] = [c["name"] for c in listed["campaigns"]]
        with pytest.raises(Exception, match="campaign 'nope': not in"):
            await asyncio.to_thread(request, sock, {"cmd": "start", "campaign": "nope"})
        with pytest.raises(Exception, match="unknown command 'dance'") as unknown:
            await asyncio.to_thread(request, sock, {"cmd": "dance"})
        out["unknown"], out["table"] = str(unknown.value), sorted(d._command_table())
        with pytest.raises(ConfigError, match="another daemon answers there"):
            from robid_link.link.control import ControlServer

            async def noop(req: dict) -> dict:
                return {}

            async with ControlServer(sock, noop):
                pass
        return out

    out = with_daemon(cfg, body)
    assert out["mode"] == 0o660 and out["pid"] == os.getpid()
    assert out["campaigns"] == ["one"]
    assert not sock.exists()  # removed on a clean stop
    # one table of commands: an unknown one is answered with one line naming the known ones
    assert out["table"] == ["approve", "cancel", "list", "params_approve", "params_rollback",
                            "ping", "results", "resume", "start", "status"]
    assert out["unknown"] == ("unknown command 'dance' (known: approve, cancel, list, "
                              "params_approve, params_rollback, ping, results, resume, start, "
                              "status)")


def test_an_internal_error_fails_the_run_not_the_daemon(tmp_path: Path, controller: Any,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    from robid_link.link import campaign

    cfg = write_config(tmp_path, {"one": ONE})

    async def broken(*args: Any, **kw: Any) -> None:
        raise ZeroDivisionError("boom")

    async def body(d: Daemon) -> tuple[dict, dict]:
        with monkeypatch.context() as m:
            m.setattr(campaign, "execute_run", broken)
            bad = await start(d)
        good = await start(d)  # the daemon still serves
        return bad, good

    with controller():
        bad, good = with_daemon(cfg, body)
    assert bad["state"] == "failed" and bad["error"] == "internal error: ZeroDivisionError: boom"
    assert good["state"] == "completed"


def test_resume_after_a_failed_attempt_takes_back_its_ready(tmp_path: Path,
                                                            controller: Any) -> None:
    """Killed between journaling a failed attempt and withdrawing it: the restart does it."""
    from robid_link.link.store import Store

    cfg = write_config(tmp_path, {"one": ONE})
    with Store(tmp_path / "state") as st:
        run_id = st.create_run("one", "operator", {"campaign": "one"},
                               [("rigid_body", "rigid_body")])
        st.step(run_id, "rigid_body", "giving", attempt=1, nonce="old1", program_sha=None)
        st.step(run_id, "rigid_body", "attempt_failed", error="no 'done' within 4 s")
    stale = tmp_path / "share" / "sem" / "rigid_body.old1.ready"
    stale.parent.mkdir(parents=True)
    stale.write_text("{}\n")

    async def body(d: Daemon) -> tuple[dict, bool]:
        store = d.store
        assert store is not None
        async with asyncio.timeout(60):  # the restart's bookkeeping takes it back, no motion
            while (await store.run(run_id))["state"] != "interrupted":
                await asyncio.sleep(0.02)
        gone = not stale.exists()
        assert (await store.experiment(run_id, "rigid_body"))["attempt"] == 1
        await d.handle({"cmd": "resume", "run_id": run_id})  # the operator's go-ahead
        with controller():
            return await wait_run(d, run_id), gone

    run, gone = with_daemon(cfg, body)
    assert gone
    assert run["state"] == "completed" and run["experiments"][0]["attempt"] == 2


class _NoUploadDriver(Driver):
    """A plug-in driver that cannot upload parameters: its hooks must never be reached."""

    name = "no_upload"
    capabilities = frozenset()
    opened = 0

    async def _open(self) -> None:
        type(self).opened += 1

    async def _close(self) -> None:
        return None

    async def _put_program(self, program: MotionProgram) -> None:
        raise AssertionError("a program reached a driver that was refused")

    async def _give_ready(self, exp_id: str, nonce: str) -> None:
        raise AssertionError("'ready' given by a driver that was refused")

    async def _wait_done(self, exp_id: str, nonce: str) -> Done:
        raise AssertionError("unreachable")

    async def _fetch_logs(self, done: Done) -> bytes:
        raise AssertionError("unreachable")


def test_upload_with_a_driver_that_cannot_is_refused_at_start(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A campaign with ``upload: true`` over a driver without CAP_UPLOAD: one line naming the
    campaign key, before the driver is opened (nothing can move), and the store is released."""
    from robid_link.link import daemon as daemon_module
    from robid_link.link.store import Store

    cfg = write_config(tmp_path, {"one": ONE, "up": {**ONE, "identify": True, "upload": True}})
    monkeypatch.setattr(daemon_module, "make_driver", lambda options: _NoUploadDriver())

    async def body(d: Daemon) -> None:
        raise AssertionError("the daemon started")

    with pytest.raises(ConfigError) as err:
        with_daemon(cfg, body)
    msg = str(err.value)
    assert "campaigns.up.upload: driver 'no_upload' cannot upload parameters" in msg, msg
    assert "\n" not in msg and str(cfg) in msg
    assert _NoUploadDriver.opened == 0
    assert not (tmp_path / "ctl.sock").exists()
    with Store(tmp_path / "state"):  # the lock was released
        pass


class _MasterDriver(_NoUploadDriver):
    """A plug-in driver that is the motion master (CAP_FEEDFORWARD): it asks for torques."""

    name = "master"
    capabilities = frozenset({CAP_FEEDFORWARD})


def test_the_daemon_gives_a_motion_master_its_torques_from_the_worker(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The daemon binds ``Driver.feedforward_table`` to a FeedforwardJob on its robot, run in a
    worker process: the table is the set's inverse dynamics plus friction (the same numbers
    as the worker's code run here), one row per setpoint; the driver computes nothing."""
    import numpy as np

    from robid_link.ident.fit.paramset import feedforward, setpoint_torque
    from robid_link.ident.model.robot import load_robot
    from robid_link.jobs import ParameterSet, set_sha256
    from robid_link.link import daemon as daemon_module

    from .conftest import ARM3

    robot = load_robot(ARM3)
    assert robot.nominal is not None
    doc = {"format": "robid-parameter-set/1", "robot": robot.name,
           "friction": {"viscous": [2.0] * 3, "coulomb": [1.5] * 3, "offset": [0.0] * 3},
           "standard_inertials": [float(x) for x in robot.nominal]}
    pset = ParameterSet.from_doc({**doc, "sha256": set_sha256(doc)})
    q = np.column_stack([0.3 * np.sin(np.linspace(0, 3, 50))] * 3) * [1.0, -1.0, 0.5]
    cfg = write_config(tmp_path, {"one": ONE})
    monkeypatch.setattr(daemon_module, "make_driver", lambda options: _MasterDriver())

    async def body(d: Daemon) -> Any:
        return await d.driver.feedforward_table(pset, 0.004, q.tolist())

    table = with_daemon(cfg, body)
    want = setpoint_torque(robot, feedforward(pset.doc, 3), q, 0.004)
    assert table.set_sha256 == pset.sha256 and len(table.tau) == len(q)
    np.testing.assert_allclose(np.array(table.tau), want, rtol=1e-12, atol=1e-12)
    assert np.abs(want).max() > 1.0  # gravity and inertia, not zeros


def test_upload_needs_identify(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"up": {**ONE, "upload": True}})  # ONE: identify false
    with pytest.raises(ConfigError, match=r"campaigns\.up\.upload: needs identify: true"):
        load_daemon_config(cfg)


def test_daemon_context_leaves_nothing_running(tmp_path: Path) -> None:
    """``async with Daemon(...)``: its loops run while inside, and leaving cancels and awaits
    them, removes the socket and releases the store."""
    from robid_link.link.store import Store

    cfg = write_config(tmp_path, {"one": ONE})

    async def go() -> tuple[list[str], list[asyncio.Task]]:
        async with Daemon(load_daemon_config(cfg), env={}) as d:
            names = sorted(t.get_name() for t in asyncio.all_tasks() if not t.done())
            tasks = list(d._tasks)
        return names, tasks

    names, tasks = asyncio.run(go())
    assert "robid-runner" in names
    assert all(t.done() for t in tasks)
    assert not (tmp_path / "ctl.sock").exists()
    with Store(tmp_path / "state"):
        pass


def test_an_error_in_the_body_leaves_the_daemon_as_itself(tmp_path: Path) -> None:
    """``async with Daemon(...)``: the body's exception comes out as it was raised (not in an
    ExceptionGroup) and the daemon is closed behind it."""
    cfg = write_config(tmp_path, {"one": ONE})

    async def go() -> None:
        async with Daemon(load_daemon_config(cfg), env={}):
            raise ConfigError("campaign 'x': not in the config")

    with pytest.raises(ConfigError, match="campaign 'x'"):
        asyncio.run(go())
    assert not (tmp_path / "ctl.sock").exists()


def test_a_program_is_generated_once_however_many_ask(tmp_path: Path,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    """The start-up pre-flight, a 'start' and a second campaign with the same experiment ask
    for one program at once: one worker generates it, the others wait for the cache (on a
    loaded two-core cell PC a duplicate generation doubled the minutes a 'start' waited)."""
    from robid_link.link import campaign as cp

    cfg = write_config(tmp_path, {"a": ONE, "b": ONE})

    async def body(d: Daemon) -> list[str]:
        got = await asyncio.gather(*(cp.prepare_programs(d.cfg, d.store, d.ctx, name)
                                     for name in ("a", "b", "a")))
        await d.handle({"cmd": "start", "campaign": "b"})  # pre-flight: from the cache
        return [prog.sha256 for progs in got for _, prog in progs]

    caplog.set_level("INFO", logger="robid.campaign")
    shas = with_daemon(cfg, body)
    assert len(set(shas)) == 1
    generated = [r for r in caplog.records if "generated" in r.getMessage()]
    assert len(generated) == 1, [r.getMessage() for r in generated]
    assert not cp._generating


def test_a_cancel_while_a_failed_attempt_is_stored_leaves_no_ready(
        tmp_path: Path, controller: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 19: the cancel reached the run while it stored a failed attempt, before that
    attempt's 'ready' was taken back; the cancel withdrew only attempts still 'given', and the
    'ready' stayed for a controller to run with nobody watching. The stop now goes out before
    the failure is stored."""
    from robid_link.link.store import SqliteStore

    cfg = write_config(tmp_path, {"one": ONE})
    real = SqliteStore.step
    storing: list[asyncio.Event] = []

    async def step(self: SqliteStore, run_id: str, exp_id: str, state: str, **kw: Any) -> None:
        await real(self, run_id, exp_id, state, **kw)  # (the store's thread commits it)
        if state == "attempt_failed" and storing:
            storing[0].set()
            await asyncio.sleep(0.5)  # the operator's cancel lands here

    monkeypatch.setattr(SqliteStore, "step", step)

    async def body(d: Daemon) -> tuple[list[str], str]:
        storing.append(asyncio.Event())
        run_id = (await d.handle({"cmd": "start", "campaign": "one"}))["run_id"]
        async with asyncio.timeout(60):
            await storing[0].wait()
        await d.handle({"cmd": "cancel", "run_id": run_id})
        ready = [n for n in os.listdir(tmp_path / "share" / "sem") if n.endswith(".ready")]
        return ready, (await d.store.run(run_id))["state"]  # type: ignore[union-attr]

    with controller(fault="fail", fault_count=3):
        ready, state = with_daemon(cfg, body)
    assert state == "cancelled" and ready == []
