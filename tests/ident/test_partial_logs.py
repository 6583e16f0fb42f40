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
    print(f"\nindustrial6 (the project's plant): {d.size} base parameters, max |Δθ|/σ "
          f"{z.max():.2f}, χ² {stat:.1f}; σ_joined/σ_full median "
          f"{np.median(np.sqrt(np.diag(joined.cov) / np.diag(ref.cov))):.2f}")
    assert z.max() < 4.0, f"max |Δθ|/σ {z.max():.2f}"
    np.testing.assert_allclose(joined.validation.rmse, ref.validation.rmse, rtol=0.1)
    # the joined σ: each joint's equation has as many rows as in the full log
    np.testing.assert_allclose(np.sqrt(np.diag(joined.cov)), np.sqrt(np.diag(ref.cov)),
                               rtol=0.35)


# ----------------------------------------------------------------------------- another plant
# A two-link arm in a vertical plane written out by hand (textbook closed form, its own motion
# and noise): data the project's simulator and regressor did not make.

PLANAR = """name: planar2
gravity: [0, -9.81, 0]
joints:
  - {name: shoulder, alpha: 0, a: 0, theta: 0, d: 0,
     limits: {q: [-180, 180], qd: 300, qdd: 900, tau: 300},
     inertial: {m: 3.0, com: [0.25, 0, 0], I: [0.04, 0, 0.04, 0, 0, 0.05]}}
  - {name: elbow, alpha: 0, a: 0.5, theta: 0, d: 0,
     limits: {q: [-180, 180], qd: 300, qdd: 900, tau: 300},
     inertial: {m: 2.0, com: [0.2, 0, 0], I: [0.02, 0, 0.02, 0, 0, 0.03]}}
"""


def _planar_run(path, torque_joints, seed, *, duration=45.0, rate=400.0, noise=0.3):
    """The arm's torque on a sum-of-sines motion (the same motion every run), with friction
    and noise of its own seed; only ``torque_joints`` logged (None: both)."""
    m1, c1, i1, m2, c2, i2, l1, g = 3.0, 0.25, 0.05, 2.0, 0.2, 0.03, 0.5, 9.81
    fv, fc = np.array([1.2, 0.8]), np.array([0.9, 0.6])
    t = np.arange(0.0, duration, 1.0 / rate)
    amp = np.array([[0.9, 0.5, 0.3], [1.1, 0.6, 0.4]])
    freq = 2 * np.pi * np.array([[0.11, 0.27, 0.43], [0.17, 0.31, 0.53]])
    phase = np.array([[0.0, 1.0, 2.0], [0.5, 1.5, 2.5]])
    arg = freq[:, :, None] * t + phase[:, :, None]
    q = (amp[:, :, None] * np.sin(arg)).sum(axis=1).T
    qd = (amp[:, :, None] * freq[:, :, None] * np.cos(arg)).sum(axis=1).T
    qdd = -(amp[:, :, None] * freq[:, :, None] ** 2 * np.sin(arg)).sum(axis=1).T
    cos2, sin2 = np.cos(q[:, 1]), np.sin(q[:, 1])
    m11 = i1 + m1 * c1**2 + i2 + m2 * (l1**2 + c2**2 + 2 * l1 * c2 * cos2)
    m12 = i2 + m2 * (c2**2 + l1 * c2 * cos2)
    m22 = i2 + m2 * c2**2
    h = m2 * l1 * c2 * sin2
    g1 = g * (m1 * c1 * np.cos(q[:, 0]) + m2 * (l1 * np.cos(q[:, 0]) + c2 * np.cos(q.sum(1))))
    g2 = g * m2 * c2 * np.cos(q.sum(axis=1))
    tau = np.column_stack([
        m11 * qdd[:, 0] + m12 * qdd[:, 1] - h * (2 * qd[:, 0] * qd[:, 1] + qd[:, 1] ** 2) + g1,
        m12 * qdd[:, 0] + m22 * qdd[:, 1] + h * qd[:, 0] ** 2 + g2])
    tau += fv * qd + fc * np.sign(qd)
    tau += np.random.default_rng(seed).normal(0.0, noise, tau.shape)
    write_log_csv(path, t, q, tau, torque_joints=torque_joints)
    return path


def test_joined_runs_match_the_full_log_on_another_plant(tmp_path):
    from robid_link.ident.model.robot import load_robot

    (tmp_path / "planar2.yaml").write_text(PLANAR)
    robot = load_robot(tmp_path / "planar2.yaml")
    full = _planar_run(tmp_path / "full.csv", None, 1)
    parts = [_planar_run(tmp_path / f"j{j}.csv", (j,), 1 + j) for j in (1, 2)]
    ref = identify(robot, load_logs(robot, [full]), DEFAULT_MODEL)
    np.testing.assert_allclose(ref.validation.rmse, 0.3, rtol=0.1)  # the model fits the arm
    joined = identify(robot, load_logs(robot, parts), DEFAULT_MODEL)
    np.testing.assert_allclose(joined.validation.rmse, 0.3, rtol=0.1)
    d = joined.theta - ref.theta
    cov = joined.cov + ref.cov
    stat = float(d @ np.linalg.solve(cov, d))
    z = np.abs(d) / np.sqrt(np.diag(cov))
    print(f"\nplanar2 (independent plant): {d.size} base parameters, max |Δθ|/σ "
          f"{z.max():.2f}, χ² {stat:.1f}")
    assert stat < chi2.ppf(0.99, d.size), f"χ² {stat:.1f} with {d.size} dof"
    assert z.max() < 4.0


def test_report_and_json_of_a_partial_validation_log(industrial6, tmp_path):
    """Validation on a log holding joints 4 and 5 only: their figures, the other joints' none
    (None in JSON, '—' in the summary), no torque figure without a measurement; the
    diagnosis refuses partial logs in one line."""
    from robid_link.ident.diagnosis.diagnose import diagnose
    from robid_link.ident.runner import run_job

    paths = _runs(industrial6, tmp_path, [(1, 2, 3), (4, 5, 6), (4, 5)], duration=10.0)
    logs = load_logs(industrial6, paths)
    out = run_job(industrial6, logs[:2], DEFAULT_MODEL, validate=logs[2:],
                  report_dir=tmp_path / "rep")
    doc = out.docs["identify"]
    assert [x is None for x in doc["rmse"]] == [True, True, True, False, False, True]
    assert doc["noise_floor"][3] is not None and doc["noise_floor"][0] is None
    row1 = next(ln for ln in out.result.summary().splitlines() if ln.startswith("   1 a1"))
    assert row1.split()[2:5] == ["—", "—", "—"]
    figs = sorted(p.name for p in (tmp_path / "rep").glob("torque_joint*.png"))
    assert figs == ["torque_joint4.png", "torque_joint5.png"]
    assert "partial logs" in (tmp_path / "rep" / "report.html").read_text()
    with pytest.raises(DataError, match=r"^run0.csv: the diagnosis needs every joint's torque"):
        diagnose(industrial6, logs[:2], DEFAULT_MODEL, result=out.result)


@pytest.mark.parametrize("method", ["wls", "irls", "consistent"])
def test_every_estimator_joins_partial_logs(industrial6, tmp_path, method):
    """WLS, IRLS and the consistent fit on joined logs (per-joint weights, robust scales and
    cross-validation folds from the rows that hold each joint's torque) validate as OLS."""
    paths = _runs(industrial6, tmp_path, [(1, 2, 3), (4, 5, 6)], duration=15.0)
    logs = load_logs(industrial6, paths)
    ols = identify(industrial6, logs, DEFAULT_MODEL)
    res = identify(industrial6, logs, DEFAULT_MODEL, method=method)
    np.testing.assert_allclose(res.validation.rmse, ols.validation.rmse, rtol=0.02)
    assert np.isfinite(res.theta).all() and np.isfinite(np.diag(res.cov)).all()
