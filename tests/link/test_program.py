"""Motion programs: generation within the limits, the safety check that refuses unsafe ones,
reduced speed, and the RAPID module parsed back into the trajectory's joint targets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robid_link.exceptions import ConfigError, UnsafeProgramError
from robid_link.ident.excite import excitation as ex
from robid_link.ident.excite import experiments as xp
from robid_link.ident.excite import program as pg
from robid_link.ident.model.robot import Robot, load_robot
from robid_link.kinds import KIND_OPTIONS, experiment_options

ROBOTS = Path(__file__).resolve().parents[2] / "examples" / "robots"


@pytest.fixture(scope="module")
def arm3() -> Robot:
    return load_robot(ROBOTS / "arm3.yaml")


@pytest.fixture(scope="module")
def fourier(arm3: Robot) -> ex.Trajectory:
    opts = experiment_options("rigid_body", {"duration_s": 10, "harmonics": 4,
                                                "evaluations": 40, "rate_hz": 100}, "e")
    return xp.experiment_trajectory(arm3, "rigid_body", opts)


def test_generated_programs_respect_every_limit(arm3: Robot, fourier: ex.Trajectory) -> None:
    sweeps = xp.experiment_trajectory(arm3, "friction",
                                      experiment_options("friction", {}, "e"))
    for traj in (fourier, sweeps):
        pg.check_program(arm3, traj, "x")  # raises if not
        q, qd, qdd = pg.program_trajectory(traj)
        assert np.all(np.abs(qd) <= arm3.limits.qd_max + 1e-9)
        assert np.all(q >= arm3.limits.q_min) and np.all(q <= arm3.limits.q_max)


def test_unsafe_program_is_refused_naming_joint_and_quantity(arm3: Robot,
                                                             fourier: ex.Trajectory) -> None:
    fast = ex.Trajectory(fourier.t / 3, fourier.q, fourier.rate_hz * 3, "custom", "arm3")
    with pytest.raises(UnsafeProgramError,
                       match=r"unsafe program refused: experiment x: qd\d = .* deg/s .*limit"):
        pg.make_program(arm3, fast, "x")
    wide = ex.Trajectory(fourier.t, fourier.q * 4, fourier.rate_hz, "custom", "arm3")
    with pytest.raises(UnsafeProgramError, match="unsafe program refused"):
        pg.make_program(arm3, wide, "x")
    nan = ex.Trajectory(fourier.t, fourier.q.copy(), fourier.rate_hz, "custom", "arm3")
    nan.q[5, 1] = np.nan
    with pytest.raises(UnsafeProgramError, match="non-finite"):
        pg.make_program(arm3, nan, "x")
    two = ex.Trajectory(fourier.t, fourier.q[:, :2], fourier.rate_hz, "custom", "arm3")
    with pytest.raises(UnsafeProgramError, match="2 joints, the robot has 3"):
        pg.make_program(arm3, two, "x")


def test_torque_limits_of_the_a_priori_model(arm3: Robot, fourier: ex.Trajectory) -> None:
    import dataclasses

    weak = dataclasses.replace(arm3, limits=dataclasses.replace(
        arm3.limits, tau_max=np.array([120.0, 1.0, 60.0])))
    with pytest.raises(UnsafeProgramError, match="a-priori model needs tau2"):
        pg.check_program(weak, fourier, "x")


def test_reduced_speed_scales_velocity_and_acceleration(fourier: ex.Trajectory) -> None:
    slow = pg.reduced_speed(fourier, 0.25)
    q, qd, qdd = pg.program_trajectory(fourier)
    qs, qds, qdds = pg.program_trajectory(slow)
    assert slow.t[-1] == pytest.approx(fourier.t[-1] / 0.25, abs=0.02)
    assert np.abs(qds).max() == pytest.approx(0.25 * np.abs(qd).max(), rel=0.01)
    assert np.abs(qdds).max() == pytest.approx(0.0625 * np.abs(qdd).max(), rel=0.02)
    np.testing.assert_allclose(qs[::4][: len(q)], q[: len(qs[::4])], atol=1e-9)


def test_program_hash_is_stable_and_content_addressed(arm3: Robot,
                                                      fourier: ex.Trajectory) -> None:
    a = pg.make_program(arm3, fourier, "rb")
    b = pg.make_program(arm3, fourier, "rb")
    assert a.sha256 == b.sha256
    assert set(a.files) == {"traj.csv", "traj.yaml"}  # neutral: drivers render their own
    assert a.trajectory().joint_types == tuple(arm3.joint_types)
    np.testing.assert_allclose(a.trajectory().q, fourier.q, atol=1e-9)
    other = ex.Trajectory(fourier.t, fourier.q * 0.9, fourier.rate_hz, "custom", "arm3")
    assert pg.make_program(arm3, other, "rb").sha256 != a.sha256


def test_experiment_options_name_the_bad_key() -> None:
    with pytest.raises(ConfigError, match=r"c\.experiments\[0\]: unknown key 'colour' \(known: "
                       r"base_hz, duration_s, evaluations"):
        experiment_options("rigid_body", {"colour": 1}, "c.experiments[0]")
    with pytest.raises(ConfigError, match=r"e\.speeds: expected fractions"):
        experiment_options("friction", {"speeds": [2.0]}, "e")
    with pytest.raises(ConfigError, match=r"e: missing key 'trajectory'"):
        experiment_options("custom", {}, "e")
    with pytest.raises(ConfigError, match=r"e\.duration_s: expected a positive number"):
        experiment_options("rigid_body", {"duration_s": -1}, "e")


def test_experiment_kinds_are_one_table() -> None:
    """Every kind the config accepts has options on the door and a generator in the worker's
    registry, in the same order."""
    assert list(xp.EXPERIMENT_KINDS) == list(KIND_OPTIONS)
    assert list(xp.EXPERIMENT_KINDS)[:3] == ["rigid_body", "friction", "custom"]
    with pytest.raises(ValueError, match="already registered"):
        xp.register_kind(xp.EXPERIMENT_KINDS["friction"])
    with pytest.raises(ValueError, match="no options"):
        xp.register_kind(xp.ExperimentKind("warp", xp.EXPERIMENT_KINDS["friction"].generate))
    with pytest.raises(ConfigError, match=r"e\.kind: expected one of rigid_body, friction"):
        experiment_options("warp", {}, "e")
