"""The RWS driver against its fake controller: the contract again over RWS 2.0 (HTTPS, Basic
auth; the shared suite runs 1.0), the controller's own faults (restart, silent websocket,
execution error, session limit), and the security rules (credentials, TLS, no secret logged)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from robid_link.drivers.abb_rws import AbbRwsDriver
from robid_link.drivers.rws_api import (
    RAPID_STRING_MAX,
    done_value,
    parse_done,
    parse_size,
    read_credentials,
    rws_module,
    size_value,
)
from robid_link.exceptions import ConfigError, DriverError, DriverTimeoutError
from robid_link.fakes.controller import default_truth, make_peer
from robid_link.ident.model.robot import Robot
from robid_link.jobs import MotionProgram, RobotInfo
from robid_link.link import registry
from robid_link.link.driver import Driver
from tests.drivers.test_contract import RATE_HZ, _cycle, _parse

HAVE_OPENSSL = shutil.which("openssl") is not None


@contextlib.contextmanager
def rws(tmp_path: Path, robot: Robot, version: int = 1, driver_over: dict[str, Any] | None
        = None, **kw: Any) -> Iterator[tuple[Driver, Any]]:
    work = tmp_path / "cell"
    work.mkdir(parents=True, exist_ok=True)
    peer = make_peer("abb_rws", robot, default_truth(robot, rate_hz=RATE_HZ), work,
                     version=version, **kw)
    with peer:
        driver = registry.make_driver({**peer.driver_options(), "backoff_s": 0.1,
                                       **(driver_over or {})})
        driver.bind_robot(RobotInfo.of(robot))
        try:
            yield driver, peer
        finally:
            asyncio.run(driver.close())


VERSIONS = pytest.mark.parametrize("version", [1, 2])


# -- the controller's own faults
@VERSIONS
def test_restart_mid_program_subscribes_again_and_asks(tmp_path: Path, robot: Robot,
                                                       program: MotionProgram, version: int,
                                                       caplog: pytest.LogCaptureFixture
                                                       ) -> None:
    with rws(tmp_path, robot, version, fault="restart", ping_interval_s=0.5) as (driver, peer):
        arr = _parse(_cycle(driver, program))
    assert arr.shape[0] >= 0.5 * RATE_HZ
    assert peer.logins == 2 and len(peer.core.handled) == 1  # a new session, no second run
    # the restart is seen as a lost subscription or, when a read comes first, as the
    # controller answering 503 while it starts: either way it is noticed, not waited out
    assert "subscription lost" in caplog.text or "HTTP 503" in caplog.text


@VERSIONS
def test_a_silent_websocket_is_noticed_by_its_missing_pings(tmp_path: Path, robot: Robot,
                                                            program: MotionProgram,
                                                            version: int,
                                                            caplog: pytest.LogCaptureFixture
                                                            ) -> None:
    with rws(tmp_path, robot, version, fault="silent_ws", ping_interval_s=0.3) as (driver, _):
        _parse(_cycle(driver, program, timeout_s=30))
    assert "no ping or event for 0.6 s" in caplog.text


def test_pings_keep_a_quiet_link_alive(tmp_path: Path, robot: Robot, program: MotionProgram,
                                       caplog: pytest.LogCaptureFixture) -> None:
    """A program longer than two ping periods: the pings, not events, keep the socket."""
    with rws(tmp_path, robot, 1, fault="never_answer", ping_interval_s=0.2) as (driver, _):
        async def go() -> None:
            async with driver:
                await driver.put_program(program)
                await driver.give_ready("exp1", "n1")
                with pytest.raises(DriverTimeoutError):
                    await driver.take_done("exp1", "n1", timeout_s=1.5)
                await driver.withdraw("exp1", "n1")

        asyncio.run(go())
    assert "subscription lost" not in caplog.text


@VERSIONS
def test_execution_error_is_reported_at_once(tmp_path: Path, robot: Robot,
                                             program: MotionProgram, version: int) -> None:
    with rws(tmp_path, robot, version, fault="exec_error") as (driver, _):
        t0 = time.monotonic()
        with pytest.raises(DriverError, match="stopped during experiment exp1") as err:
            _cycle(driver, program, timeout_s=60)
    assert not isinstance(err.value, DriverTimeoutError) and time.monotonic() - t0 < 30


@VERSIONS
def test_session_limit_is_waited_out_with_bounded_backoff(tmp_path: Path, robot: Robot,
                                                          program: MotionProgram,
                                                          version: int) -> None:
    with rws(tmp_path, robot, version, fault="session_limit", fault_count=2) as (driver, peer):
        _parse(_cycle(driver, program))
    assert peer.logins == 1 and peer.auth_attempts == 3


def test_session_limit_that_persists_is_one_error(tmp_path: Path, robot: Robot) -> None:
    with rws(tmp_path, robot, 1, fault="session_limit", fault_count=100,
             driver_over={"retries": 2}) as (driver, peer):
        with pytest.raises(DriverError, match=r"login: controller unavailable after 3 "
                                              r"attempts \(HTTP 503"):
            asyncio.run(driver.open())
    assert peer.auth_attempts == 3


def test_withdraw_stops_the_program_and_the_next_attempt_runs(tmp_path: Path, robot: Robot,
                                                              program: MotionProgram) -> None:
    with rws(tmp_path, robot, 2, fault="never_answer") as (driver, peer):
        async def go() -> bytes:
            async with driver:
                await driver.put_program(program)
                await driver.give_ready("exp1", "n1")
                with pytest.raises(DriverTimeoutError):
                    await driver.take_done("exp1", "n1", timeout_s=0.5)
                await driver.withdraw("exp1", "n1")
                assert peer.exec_state == "stopped"
                await driver.put_program(program)
                await driver.give_ready("exp1", "n2")
                done = await driver.take_done("exp1", "n2", timeout_s=30)
                return await driver.fetch_logs(done)

        _parse(asyncio.run(go()))
    assert [n for _, n in peer.core.handled] == ["n1", "n2"]


def test_a_running_program_is_not_started_twice_by_a_restarted_daemon(
        tmp_path: Path, robot: Robot, program: MotionProgram) -> None:
    with rws(tmp_path, robot, 1, fault="never_answer") as (driver, peer):
        async def go() -> None:
            async with driver:
                await driver.put_program(program)
                await driver.give_ready("exp1", "n1")
            again = registry.make_driver(peer.driver_options())  # the daemon came back
            async with again:
                await again.put_program(program)  # same experiment running: left alone
                await again.give_ready("exp1", "n1")
                with pytest.raises(DriverError, match="running; refusing to start"):
                    await again.give_ready("exp2", "n9")
                await again.withdraw("exp1", "n1")

        asyncio.run(go())
    assert peer.core.handled == [("exp1", "n1")]


def _pset(robot: Robot) -> dict[str, Any]:
    from robid_link.ident.fit.paramset import make_parameter_set

    names = [f"{p}_{j}" for p in ("fv", "fc") for j in (1, 2, 3)]
    return make_parameter_set(robot, {"effects": ["viscous", "coulomb"], "parameters": [
        {"name": n, "value": 1.0 + k, "std": 0.1, "expression": n}
        for k, n in enumerate(names)]}, run_id="run1")


@VERSIONS
def test_upload_parameters_is_loaded_and_acknowledged(tmp_path: Path, robot: Robot,
                                                      version: int) -> None:
    doc = _pset(robot)
    with rws(tmp_path, robot, version) as (driver, peer):
        async def go() -> None:
            async with driver:
                await driver.upload_parameters(doc, timeout_s=20)

        asyncio.run(go())
    assert peer.core.feedforward.sha256 == doc["sha256"]
    assert peer.vars["robid_params"].startswith("$HOME/robid/params/arm3.")
    assert peer.vars["robid_params_ack"].endswith(" OK")


def test_unacknowledged_or_refused_parameters(tmp_path: Path, robot: Robot) -> None:
    doc = _pset(robot)
    with rws(tmp_path / "a", robot, 1, fault="no_param_ack") as (driver, peer):
        with pytest.raises(DriverTimeoutError, match="did not acknowledge parameter set"):
            asyncio.run(_upload(driver, doc, 1.0))
        assert peer.core.feedforward is None and peer.vars["robid_params"] == ""
    with rws(tmp_path / "b", robot, 1) as (driver, peer):
        bad = {**doc, "friction": {"viscous": [1.0]}}
        # the controller's whole reason fits in its 80-character RAPID string
        with pytest.raises(DriverError, match=r"refused parameter set .*: damaged \(sha256 "
                                              r"mismatch\)"):
            asyncio.run(_upload(driver, bad, 20.0))
        assert len(peer.vars["robid_params_ack"]) <= 80
        assert peer.core.feedforward is None


async def _upload(driver: Any, doc: dict[str, Any], timeout_s: float) -> None:
    async with driver:
        await driver.upload_parameters(doc, timeout_s=timeout_s)


# -- security
@VERSIONS
def test_wrong_credentials_are_one_line_and_no_retry_storm(tmp_path: Path, robot: Robot,
                                                           version: int) -> None:
    with rws(tmp_path, robot, version, fault="bad_credentials") as (driver, peer):
        with pytest.raises(DriverError) as err:
            asyncio.run(driver.open())
    msg = str(err.value)
    assert "login refused (HTTP 401)" in msg and "\n" not in msg
    assert peer._password not in msg and peer.auth_attempts <= 2


def test_credentials_readable_by_others_are_refused(tmp_path: Path) -> None:
    cred = tmp_path / "cred"
    cred.write_text("robid:secret-pw\n")
    cred.chmod(0o644)
    with pytest.raises(ConfigError, match=r"driver\.credentials_file: .* readable by others "
                                          r"\(mode 0644\); chmod 600") as err:
        AbbRwsDriver(url="http://127.0.0.1:1", version=1, credentials_file=str(cred))
    assert "secret-pw" not in str(err.value)
    cred.chmod(0o600)
    assert read_credentials(cred) == ("robid", "secret-pw")
    cred.write_text("user: Default User\npassword: 'a:b'\n")
    assert read_credentials(cred) == ("Default User", "a:b")


@pytest.mark.skipif(not HAVE_OPENSSL, reason="the openssl tool makes the test certificate")
def test_tls_verification_failure_is_refused_unless_disabled(tmp_path: Path,
                                                             robot: Robot) -> None:
    with rws(tmp_path, robot, 2, driver_over={"ca_file": None}) as (driver, _):
        with pytest.raises(DriverError, match="TLS certificate verification failed") as err:
            asyncio.run(driver.open())
        assert "\n" not in str(err.value) and "insecure_skip_verify" in str(err.value)
    with rws(tmp_path, robot, 2, driver_over={"ca_file": None, "verify_tls": False,
                                              "insecure_skip_verify": True}) as (driver, _):
        async def go() -> None:
            async with driver:  # explicitly disabled: connects
                pass

        asyncio.run(go())
    with pytest.raises(ConfigError, match=r"driver\.verify_tls: false needs "
                                          r"driver\.insecure_skip_verify"):
        with rws(tmp_path, robot, 2, driver_over={"verify_tls": False}):
            pass


@VERSIONS
def test_no_secret_in_any_log(tmp_path: Path, robot: Robot, program: MotionProgram,
                              version: int, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    with rws(tmp_path, robot, version, fault="restart") as (driver, peer):
        _cycle(driver, program)
    secrets = [peer._password, *peer.issued]
    assert peer.issued and not any(s in caplog.text for s in secrets)
    assert "session 1 opened" in caplog.text  # the peer does log, without secrets


def test_basic_auth_over_plain_http_is_refused_off_loopback(tmp_path: Path) -> None:
    cred = tmp_path / "cred"
    cred.write_text("robid:pw\n")
    cred.chmod(0o600)
    with pytest.raises(ConfigError, match=r"driver\.url: RWS 2\.0 .* use https://"):
        AbbRwsDriver(url="http://10.0.0.5", version=2, credentials_file=str(cred))


# -- config and protocol pieces
@pytest.mark.parametrize(("over", "key"), [
    ({"version": None}, "version"), ({"version": 3}, "version"), ({"url": "ftp://x"}, "url"),
    ({"url": None}, "url"), ({"credentials_file": None}, "credentials_file"),
    ({"credentials_file": "/nonexistent/cred"}, "credentials_file"), ({"task": "1x"}, "task"),
    ({"module": "a b"}, "module"), ({"ping_interval_s": 0}, "ping_interval_s"),
    ({"retries": -1}, "retries"), ({"ca_file": "/nonexistent.pem"}, "ca_file"),
    ({"insecure_skip_verify": "yes"}, "insecure_skip_verify")])
def test_config_errors_name_the_key(tmp_path: Path, over: dict[str, Any], key: str) -> None:
    cred = tmp_path / "cred"
    cred.write_text("robid:pw\n")
    cred.chmod(0o600)
    opts = {"url": "https://127.0.0.1:1", "version": 2, "credentials_file": str(cred), **over}
    with pytest.raises(ConfigError, match=rf"^driver\.{key}: "):
        AbbRwsDriver(**opts)


def test_done_values_and_the_module_name(program: MotionProgram) -> None:
    assert parse_done("") is None
    assert parse_done("n1 " + "a" * 64) == ("done", "n1", "a" * 64)
    assert parse_done("ERR n1 motion supervision") == ("error", "n1", "motion supervision")
    with pytest.raises(DriverError, match="robid_done"):
        parse_done("n1 nothex")
    with pytest.raises(DriverError, match="robid_done"):  # the old three-field value
        parse_done("n1 " + "a" * 64 + " 12")
    # a RAPID string holds 80 characters: the done value of an 8-character nonce takes 73,
    # whatever the log's size (the size has its own variable)
    assert len(done_value("3f9a0c21", "a" * 64)) == 73 <= RAPID_STRING_MAX
    assert parse_size(size_value("3f9a0c21", 10**9), "3f9a0c21") == 10**9
    with pytest.raises(DriverError, match="before 'done'"):
        parse_size("0ld0n0ce 12", "3f9a0c21")
    with pytest.raises(DriverError, match="robid_size"):
        parse_size("3f9a0c21 -12", "3f9a0c21")
    from robid_link.drivers.rapid import render_rapid

    text = rws_module(render_rapid(program)).decode()
    assert text.startswith("MODULE robid_path") and "PROC robid_move()" in text
    assert "experiment exp1," in text


def test_a_log_of_over_a_megabyte_fits_the_rapid_strings(tmp_path: Path, robot: Robot) -> None:
    """Issue 19: '<nonce> <sha256> <size>' in robid_done passed RAPID's 80 characters from
    1 MB on (the controller fails writing it); the size now has robid_size of its own."""
    from tests.drivers.conftest import bump_program

    program = bump_program(robot, 14.0, 0.05)
    work = tmp_path / "cell"
    work.mkdir()
    peer = make_peer("abb_rws", robot, default_truth(robot, rate_hz=1000.0), work)
    with peer:
        driver = registry.make_driver(peer.driver_options())
        driver.bind_robot(RobotInfo.of(robot))
        data = _cycle(driver, program)
    assert len(data) > 1_000_000
    assert all(len(v) <= RAPID_STRING_MAX for v in peer.vars.values())
    assert peer.vars["robid_size"].endswith(f" {len(data)}")
