"""Partial logs (a controller's signal budget: every axis' position, some axes' torque) joined
in one identification: each joint's equation from the logs that hold its torque."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from robid_link.exceptions import DataError
from robid_link.fakes.plant import Plant, Truth, perturbed_inertials
from robid_link.ident.data.logs import load_log, write_log_csv
from robid_link.ident.excite.excitation import random_fourier
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL

FRICTION = ({"name": "viscous", "fv": 2.0}, {"name": "coulomb", "fc": 1.5})


def _runs(robot, tmp_path, torque_joints, *, seed=5, duration=30.0, rate=400.0, noise=0.6):
    """One excitation motion run once per entry of ``torque_joints`` (None: a full log), each
    run with its own noise (a run of the same program on the controller)."""
    traj = random_fourier(robot, harmonics=5, base_hz=0.1, seed=seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    q, qd, qdd = traj.evaluate(t)
    truth = Truth(perturbed_inertials(robot, seed + 100), effects=FRICTION, noise_tau=noise)
    paths = []
    for k, joints in enumerate(torque_joints):
        out = Plant(robot, truth).run(t, q, qd, qdd, seed=seed + 200 + k)
        path = tmp_path / f"run{k}.csv"
        write_log_csv(path, out["t"], out["q"], out["tau"], torque_joints=joints)
        paths.append(path)
    return paths


def test_partial_csv_loads_with_its_held_joints(industrial6, tmp_path):
    (path,) = _runs(industrial6, tmp_path, [(1, 2, 3)], duration=2.0)
    header = path.read_text().splitlines()[0].split(",")
    assert [h for h in header if h.startswith("tau")] == ["tau1", "tau2", "tau3"]
    log = load_log(path, industrial6.n)
    assert log.partial and log.held.tolist() == [True] * 3 + [False] * 3
    assert np.isfinite(log.tau[:, :3]).all() and np.isnan(log.tau[:, 3:]).all()


def test_partial_npz_loads_with_torque_joints(industrial6, tmp_path):
    t = np.arange(0.0, 1.0, 0.01)
    q = np.zeros((t.size, 6))
    np.savez(tmp_path / "p.npz", t=t, q=q, tau=np.ones((t.size, 2)),
             torque_joints=np.array([5, 6]))
    log = load_log(tmp_path / "p.npz", 6)
    assert log.held.tolist() == [False] * 4 + [True] * 2
    np.savez(tmp_path / "bad.npz", t=t, q=q, tau=np.ones((t.size, 3)),
             torque_joints=np.array([5, 6]))
    with pytest.raises(DataError, match="bad.npz: array 'tau' has 3 joints, torque_joints "
                                        "names 2"):
        load_log(tmp_path / "bad.npz", 6)


def test_a_log_without_any_torque_is_refused(industrial6, tmp_path):
    (path,) = _runs(industrial6, tmp_path, [(1,)], duration=1.0)
    text = path.read_text().splitlines()
    path.write_text("\n".join(",".join(r.split(",")[:-1]) for r in text) + "\n")
    with pytest.raises(DataError, match=r"run0.csv: column tau1 missing \(or i1"):
        load_log(path, industrial6.n)


def test_a_joint_no_log_holds_is_named(industrial6, tmp_path):
    paths = _runs(industrial6, tmp_path, [(1, 2, 3), (4, 5)], duration=3.0)
    with pytest.raises(DataError, match=r"^joint 6 \(\w+\): no log holds its torque \(tau6 in "
                                        r"none of run0.csv, run1.csv\)$"):
        identify(industrial6, load_logs(industrial6, paths), DEFAULT_MODEL)


def test_columns_split_into_two_logs_give_the_full_logs_fit(industrial6, tmp_path):
    """The same samples, their torque columns in two files: each joint's equation gets the
    same rows, so the same θ (to rounding) and the same held-out figures per joint."""
    (full,) = _runs(industrial6, tmp_path, [None], duration=20.0)
    log = load_log(full, 6)
    for name, joints in (("a.csv", (1, 2, 3)), ("b.csv", (4, 5, 6))):
        write_log_csv(tmp_path / name, log.t, log.q, log.tau, torque_joints=joints)
    ref = identify(industrial6, load_logs(industrial6, [full]), DEFAULT_MODEL)
    joined = identify(industrial6, load_logs(industrial6, [tmp_path / "a.csv",
                                                           tmp_path / "b.csv"]), DEFAULT_MODEL)
    np.testing.assert_allclose(joined.theta, ref.theta, rtol=1e-7,
                               atol=1e-9 * np.abs(ref.theta).max())
    np.testing.assert_allclose(joined.validation.rmse, ref.validation.rmse, rtol=1e-9)
    np.testing.assert_allclose(joined.noise_floor, ref.noise_floor, rtol=1e-9)
    assert any("partial logs joined" in n and "a.csv τ1,2,3" in n for n in joined.notes)


def test_joined_runs_match_the_full_log_within_sigma(industrial6, tmp_path):
    """The original tool's budget: the excitation run twice, main axes' torques logged in one
    run, wrist axes' in the other, joined; against one run logging all six. Independent
    noise in every run: θ_joined − θ_full is within the two estimates' σ (χ² at 99 %), and
    the joined estimate agrees with the truth as the full one does."""
    paths = _runs(industrial6, tmp_path, [None, (1, 2, 3), (4, 5, 6)])
    ref = identify(industrial6, load_logs(industrial6, paths[:1]), DEFAULT_MODEL)
    joined = identify(industrial6, load_logs(industrial6, paths[1:]), DEFAULT_MODEL)
    d = joined.theta - ref.theta
    cov = joined.cov + ref.cov
    stat = float(d @ np.linalg.solve(cov, d))
    assert stat < chi2.ppf(0.99, d.size), f"χ² {stat:.1f} with {d.size} dof"
    z = np.abs(d) / np.sqrt(np.diag(cov))
    assert z.max() < 4.0, f"max |Δθ|/σ {z.max():.2f}"
    np.testing.assert_allclose(joined.validation.rmse, ref.validation.rmse, rtol=0.1)
    # the joined σ: each joint's equation has as many rows as in the full log
    np.testing.assert_allclose(np.sqrt(np.diag(joined.cov)), np.sqrt(np.diag(ref.cov)),
                               rtol=0.35)
