"""Excitation design: limits on the sampled trajectory, conditioning against random ones."""

from __future__ import annotations

import os

import numpy as np
import pytest

from robid_link.exceptions import ConfigError
from robid_link.ident.excite.excitation import (
    Trajectory,
    check_limits,
    constant_velocity_sweeps,
    excitation_condition,
    optimize_fourier,
    random_fourier,
    read_trajectory,
    stepped_sine,
    trajectory_states,
    write_trajectory,
)


def _within_limits(robot, q, qd, qdd):
    lim = robot.limits
    assert np.all(q >= lim.q_min - 1e-9) and np.all(q <= lim.q_max + 1e-9)
    assert np.all(np.abs(qd) <= lim.qd_max + 1e-9)
    assert np.all(np.abs(qdd) <= lim.qdd_max + 1e-9)


@pytest.mark.parametrize("budget", [
    {"evaluations": 200, "restarts": 1},  # make test: a short search gets there (3.1×; 18 s CPU)
    pytest.param({}, marks=pytest.mark.slow, id="default"),  # make validate: 3 × 2500
])
def test_optimized_excitation_beats_random_threefold(industrial6, budget):
    if not budget and not os.environ.get("ROBID_VALIDATE"):
        pytest.skip("make validate")
    traj, cond = optimize_fourier(industrial6, harmonics=8, base_hz=0.1, seed=0, **budget)
    t = np.arange(0.0, 2 * traj.period_s, 0.002)  # the sampled trajectory, two periods
    q, qd, qdd = traj.evaluate(t)
    _within_limits(industrial6, q, qd, qdd)
    tau = np.stack([industrial6.rnea(q[k], qd[k], qdd[k]) for k in range(0, t.size, 25)])
    assert np.all(np.abs(tau) <= industrial6.limits.tau_max)
    np.testing.assert_allclose(qd[0], 0.0, atol=1e-9)  # starts (and ends) at rest
    np.testing.assert_allclose(qdd[0], 0.0, atol=1e-9)
    rand = [excitation_condition(industrial6, random_fourier(industrial6, harmonics=8,
                                                             base_hz=0.1, seed=100 + s))
            for s in range(20)]
    assert cond * 3 <= np.median(rand), f"optimized {cond:.3g}, random median {np.median(rand):.3g}"


def test_random_fourier_respects_limits(arm3):
    traj = random_fourier(arm3, harmonics=5, base_hz=0.2, seed=3)
    q, qd, qdd = traj.evaluate(np.arange(0.0, traj.period_s, 0.001))
    _within_limits(arm3, q, qd, qdd)


def test_sweeps_and_stepped_sine(arm3):
    q = constant_velocity_sweeps(arm3, 1, speeds=[0.2, 0.8], rate_hz=500.0)
    qd = np.gradient(q[:, 1], 1 / 500.0)
    assert q.shape[1] == 3 and np.ptp(q[:, 0]) == 0.0
    assert qd.max() == pytest.approx(0.8, rel=0.02) and qd.min() == pytest.approx(-0.8, rel=0.02)
    plateau = np.abs(np.abs(qd) - 0.2) < 0.005
    assert plateau.mean() > 0.1  # constant-velocity stretches in both directions
    s = stepped_sine(arm3, 2, np.zeros(3), [2.0, 5.0], 0.01, 500.0)
    assert np.abs(s[:, 2]).max() <= 0.01 + 1e-12 and s[0, 2] == 0.0


def test_trajectory_file_roundtrip_and_errors(arm3, tmp_path):
    traj = random_fourier(arm3, seed=1)
    t = np.arange(0.0, 10.0, 0.004)
    q = traj.evaluate(t)[0]
    csv, header = write_trajectory(tmp_path / "x.csv", Trajectory(t, q, 250.0, "fourier", "arm3",
                                                                  {"base_hz": 0.1}))
    back = read_trajectory(csv)
    np.testing.assert_allclose(back.q, q, rtol=1e-9)
    assert back.kind == "fourier" and back.header["base_hz"] == 0.1
    header.write_text("rate_hz: 250\nkind: banana\n")
    with pytest.raises(ConfigError, match="kind: expected fourier"):
        read_trajectory(csv)
    header.unlink()
    with pytest.raises(ConfigError, match="header file x.yaml not found"):
        read_trajectory(csv)


def test_states_at_the_files_samples_are_the_cubic_splines():
    """At its own samples a sampled trajectory's q̇ and q̈ are the not-a-knot spline's (taken
    from its conditions, not its coefficients); elsewhere the spline itself."""
    from scipy.interpolate import CubicSpline

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 3.0, 1 / 500.0)
    q = np.column_stack((np.sin(2.1 * t), np.cos(7 * t) * t)) + 1e-4 * rng.normal(size=(t.size, 2))
    spline = CubicSpline(t, q, axis=0)
    for rate in (500.0, 1000.0):
        tt, qq, qd, qdd = trajectory_states(Trajectory(t, q, 500.0, "custom", "x"), rate)
        np.testing.assert_allclose(qq, spline(tt), rtol=0, atol=1e-12)
        np.testing.assert_allclose(qd, spline(tt, 1), rtol=0, atol=1e-9 * np.abs(qd).max())
        np.testing.assert_allclose(qdd, spline(tt, 2), rtol=0, atol=1e-9 * np.abs(qdd).max())


def test_check_limits_names_joint_and_quantity(arm3):
    q = np.zeros((5, 3))
    qd = np.zeros((5, 3))
    qd[3, 1] = 3.0  # rad/s, above 120 deg/s
    with pytest.raises(ConfigError, match=r"prog: qd2 = 171.9 deg/s at sample 4 exceeds the "
                                          r"limit 120 deg/s"):
        check_limits(arm3, q, qd, np.zeros((5, 3)), where="prog")
