"""The simulated robot: each effect does what its physics says; the truth file's errors."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
import scipy.signal as sig

from robid_link.exceptions import ConfigError
from robid_link.fakes.plant import Plant, Truth, load_truth, spring_torque
from robid_link.ident.excite.excitation import random_fourier
from robid_link.ident.model.effects import V_REST
from robid_link.ident.model.robot import load_robot


@pytest.fixture(scope="module")
def motion(arm3):
    traj = random_fourier(arm3, harmonics=5, base_hz=0.1, seed=4)
    t = np.arange(0.0, 20.0, 0.002)
    return (t, *traj.evaluate(t))


def _extra(arm3, motion, effect):
    """Torque an effect adds to the noise-free inverse-dynamics log."""
    t, q, qd, qdd = motion
    base = Plant(arm3, Truth(arm3.nominal)).run(t, q, qd, qdd)["tau"]
    with_e = Plant(arm3, Truth(arm3.nominal, effects=(effect,))).run(t, q, qd, qdd)["tau"]
    return with_e - base, (t, q, qd, qdd)


def _moving(v: np.ndarray) -> np.ndarray:
    """sign(v) of a moving joint; a resting one (|v| ≤ V_REST) has static friction only."""
    return np.where(np.abs(v) > V_REST, np.sign(v), 0.0)


def test_friction_laws(arm3, motion):
    d, (t, q, qd, qdd) = _extra(arm3, motion, {"name": "viscous", "joint": 2, "fv": 2.5})
    np.testing.assert_allclose(d[:, 1], 2.5 * qd[:, 1], atol=1e-9)
    assert np.all(d[:, [0, 2]] == 0)
    d, _ = _extra(arm3, motion, {"name": "coulomb_asymmetric", "joint": 1, "fc_pos": 3.0,
                                 "fc_neg": 1.0})
    moving = np.abs(qd[:, 0]) > 1e-6
    np.testing.assert_allclose(d[moving, 0], np.where(qd[moving, 0] > 0, 3.0, -1.0), atol=1e-9)
    d, _ = _extra(arm3, motion, {"name": "friction_power", "joint": 3, "fc": 1.0, "fv": 2.0,
                                 "alpha": 0.5, "b": 0.3})
    v = qd[:, 2]
    np.testing.assert_allclose(d[:, 2], (1 + 2 * np.sqrt(np.abs(v))) * _moving(v) + 0.3,
                               atol=1e-9)


def test_stribeck_curve(arm3, motion):
    e = {"name": "stribeck", "joint": 1, "fs": 5.0, "fc": 2.0, "vs": 0.05, "shape": 2.0, "fv": 1.0}
    d, (t, q, qd, qdd) = _extra(arm3, motion, e)
    v = qd[:, 0]
    slow = (np.abs(v) > V_REST) & (np.abs(v) < 0.002)
    fast = np.abs(v) > 0.5
    # near standstill the breakaway level fs, far above vs Coulomb plus viscous
    np.testing.assert_allclose(np.abs(d[slow, 0]), 5.0, rtol=0.01)
    np.testing.assert_allclose(d[fast, 0], 2.0 * np.sign(v[fast]) + v[fast], rtol=1e-6)


def test_armature_and_offset(arm3, motion):
    d, (t, q, qd, qdd) = _extra(arm3, motion, {"name": "armature", "joint": 3, "ia": 0.7})
    np.testing.assert_allclose(d[:, 2], 0.7 * qdd[:, 2], atol=1e-9)
    d, _ = _extra(arm3, motion, {"name": "offset", "b": -0.4})
    np.testing.assert_allclose(d, -0.4, atol=1e-12)


def test_spring_is_minus_the_gradient_of_its_potential():
    k, a, b, l0, phi = 4000.0, 0.08, 0.25, 0.12, 0.3
    q = np.linspace(-2.0, 2.0, 101)

    def energy(x):
        length = np.sqrt(a * a + b * b - 2 * a * b * np.cos(x + phi))
        return 0.5 * k * (length - l0) ** 2

    eps = 1e-6
    numeric = -(energy(q + eps) - energy(q - eps)) / (2 * eps)
    np.testing.assert_allclose(spring_torque(k, a, b, l0, phi, q), numeric, rtol=1e-6, atol=1e-6)
    # strongly nonlinear in the angle: not a sine (a spring's first harmonic)
    tau = spring_torque(k, a, b, l0, phi, q)
    fit = np.linalg.lstsq(np.column_stack((np.sin(q), np.cos(q), np.ones_like(q))), tau,
                          rcond=None)[0]
    resid = tau - np.column_stack((np.sin(q), np.cos(q), np.ones_like(q))) @ fit
    assert np.abs(resid).max() > 0.05 * np.abs(tau).max()


def test_ripple_is_periodic_in_position(arm3, motion):
    e = {"name": "ripple", "joint": 2, "amplitude": 0.8, "period": 0.2, "phase": 0.5}
    d, (t, q, qd, qdd) = _extra(arm3, motion, e)
    np.testing.assert_allclose(d[:, 1], 0.8 * np.sin(2 * np.pi * q[:, 1] / 0.2 + 0.5), atol=1e-9)


def test_friction_drift_relaxes_with_its_time_constant(arm3, motion):
    e = {"name": "friction_drift", "joint": 1, "fc": 1.0, "fv": 2.0, "change": 0.5, "tau_s": 5.0}
    d, (t, q, qd, qdd) = _extra(arm3, motion, e)
    v = qd[:, 0]
    base = _moving(v) + 2.0 * v
    ok = np.abs(base) > 0.5
    scale = d[ok, 0] / base[ok]
    np.testing.assert_allclose(scale, 1 + 0.5 * np.exp(-t[ok] / 5.0), rtol=1e-9)


def test_load_friction_grows_with_load(arm3, motion):
    t, q, qd, qdd = motion
    rigid = Plant(arm3, Truth(arm3.nominal)).rigid_torque(q, qd, qdd)
    d, _ = _extra(arm3, motion, {"name": "load_friction", "joint": 2, "mu": 0.05})
    np.testing.assert_allclose(d[:, 1], 0.05 * np.abs(rigid[:, 1]) * _moving(qd[:, 1]),
                               atol=1e-9)


def test_delay_shifts_the_torque_log(arm3, motion):
    t, q, qd, qdd = motion
    base = Plant(arm3, Truth(arm3.nominal)).run(t, q, qd, qdd)["tau"]
    late = Plant(arm3, Truth(arm3.nominal, effects=({"name": "delay", "seconds": 0.012},))
                 ).run(t, q, qd, qdd)["tau"]
    inner = slice(100, -100)
    expected = np.interp(t - 0.012, t, base[:, 1])
    np.testing.assert_allclose(late[inner, 1], expected[inner], atol=1e-9)
    lags = np.arange(-20, 21)
    err = [np.abs(late[inner, 1] - np.roll(base[:, 1], k)[inner]).mean() for k in lags]
    assert lags[int(np.argmin(err))] * (t[1] - t[0]) == pytest.approx(0.012, abs=0.002)


def test_payload_adds_its_gravity_torque(arm3):
    q = np.array([0.3, 0.4, -0.6])
    mass, com = 2.0, [0.1, 0.02, 0.0]
    plant = Plant(arm3, Truth(arm3.nominal))
    loaded = Plant(arm3, Truth(arm3.nominal, effects=({"name": "payload", "mass": mass,
                                                        "com": com},)))
    z = np.zeros((1, 3))
    diff = loaded.rigid_torque(q[None], z, z)[0] - plant.rigid_torque(q[None], z, z)[0]
    data = arm3.model.createData()
    pin.forwardKinematics(arm3.model, data, q)
    p = data.oMi[3].act(np.array(com))
    g = arm3.gravity
    expected = [-mass * np.cross(data.oMi[j + 1].rotation[:, 2],
                                 p - data.oMi[j + 1].translation) @ g for j in range(3)]
    np.testing.assert_allclose(diff, expected, rtol=1e-9, atol=1e-9)


def test_two_mass_joint_resonance(tmp_path):
    """Open loop: motor torque → motor acceleration resonates at √(K(Jm+Ja)/(Jm·Ja))/2π."""
    desc = tmp_path / "one.yaml"
    desc.write_text("name: one\nallow_unlimited: true\njoints:\n"
                    "  - {name: j, alpha: 0, a: 0, theta: 0, d: 0.2, "
                    "inertial: {m: 2.0, com: [0, 0, 0], I: [0.03, 0, 0.03, 0, 0, 0.05]}}\n")
    robot = load_robot(desc)
    k, jm, ja = 400.0, 0.02, 0.05
    truth = Truth(robot.nominal, effects=({"name": "elasticity", "k": k, "d": 0.02, "jm": jm},),
                  mode="closed_loop", controller={"rate_hz": 1000.0})
    fs = 1000.0
    t = np.arange(0.0, 30.0, 1.0 / fs)
    torque = np.random.default_rng(0).normal(size=(t.size, 1))
    log = Plant(robot, truth).run_open_loop(t, torque, np.zeros(1))
    motor_acc = np.gradient(log["qd"][:, 0], 1.0 / fs)
    f, pxy = sig.csd(torque[:, 0], motor_acc, fs=fs, nperseg=4096)
    _, pxx = sig.welch(torque[:, 0], fs=fs, nperseg=4096)
    mag = np.abs(pxy / pxx)
    band = (f > 2) & (f < 100)
    i = np.flatnonzero(band)[np.argmax(mag[band])]
    y0, y1, y2 = np.log(mag[i - 1: i + 2])
    peak = f[i] + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) * (f[1] - f[0])
    expected = math.sqrt(k * (jm + ja) / (jm * ja)) / (2 * math.pi)
    assert peak == pytest.approx(expected, rel=0.02)


def test_compiled_loop_is_the_python_loop(industrial6, monkeypatch):
    """The compiled closed and open loop (fakes/plant_kernel.py) step as Plant._integrate:
    elastic joints (one with a third mass), viscous friction and Coulomb friction whose
    stick-slip step runs at every reversal, a controller faster than the log."""
    traj = random_fourier(industrial6, harmonics=5, base_hz=0.2, seed=2)
    t = np.arange(0.0, 1.0, 0.001)
    effects = ({"name": "elasticity", "joint": 2, "k": 2e4, "d": 20.0, "jm": 2.0, "j2": 0.0,
                "k2": 0.0, "d2": 0.0},
               {"name": "elasticity", "joint": 5, "k": 300.0, "d": 0.2, "jm": 0.01,
                "j2": 0.005, "k2": 200.0, "d2": 0.1},
               {"name": "viscous", "fv": 1.0}, {"name": "coulomb", "fc": 3.0})
    plant = Plant(industrial6, Truth(industrial6.nominal * 1.02, effects=effects,
                                     mode="closed_loop", controller={"rate_hz": 2000.0}))
    states = traj.evaluate(t)
    tau = np.random.default_rng(0).normal(size=(t.size, 6)) * 20
    assert plant._compiled()
    fast = [plant.run(t, *states), plant.run_open_loop(t, tau, states[0][0])]
    monkeypatch.setattr(Plant, "_compiled", lambda self: False)
    slow = [plant.run(t, *states), plant.run_open_loop(t, tau, states[0][0])]
    for a, b in zip(fast, slow, strict=True):
        assert np.any(np.diff(np.sign(b["qd"]), axis=0) != 0)  # friction reverses
        for key in ("q", "qd", "qdd", "tau"):
            np.testing.assert_allclose(a[key], b[key], rtol=0,
                                       atol=1e-9 * np.abs(b[key]).max())


def test_composite_mass_matrix_is_pinocchio_crba(industrial6, tmp_path):
    """The plant loop's mass matrix (composite rigid body) on a serial arm, prismatic joints
    and a branched tree."""
    from robid_link.fakes.plant_kernel import composite_mass_matrix, model_params
    from robid_link.ident.model.dynamics import placements
    from robid_link.ident.model.regressor import robot_arrays

    (tmp_path / "cart.yaml").write_text(
        "name: cart\nallow_unlimited: true\njoints:\n"
        "  - {name: rail, type: prismatic, alpha: 0, a: 0, theta: 30, d: 0.2}\n"
        "  - {name: shoulder, alpha: -90, a: 0.1, theta: -90, d: 0.05}\n"
        "  - {name: slide, type: prismatic, alpha: 90, a: 0.3, theta: 10, d: -0.1}\n"
        "  - {name: wrist, alpha: 45, a: 0.05, theta: 20, d: 0.1}\n")
    inertial = ('<inertial><origin xyz="0.1 0.02 -0.03" rpy="0.1 0.2 0.3"/><mass value="{}"/>'
                '<inertia ixx="0.3" ixy="0.01" ixz="0.02" iyy="0.4" iyz="0.03" izz="0.5"/>'
                '</inertial>')
    joint = ('<joint name="{}" type="{}"><parent link="{}"/><child link="{}"/><origin '
             'xyz="0.1 0.2 0.3" rpy="0.3 -0.2 0.1"/><axis xyz="{}"/><limit lower="-3" '
             'upper="3" effort="10" velocity="2"/></joint>')
    (tmp_path / "tree.urdf").write_text(
        '<robot name="tree"><link name="base"/>'
        + "".join(f'<link name="{n}">{inertial.format(m)}</link>'
                  for n, m in (("a", 2.0), ("b", 1.5), ("c", 1.0), ("e", 0.7)))
        + joint.format("j1", "revolute", "base", "a", "0 0 1")
        + joint.format("j2", "revolute", "a", "b", "0 1 0")
        + joint.format("j3", "prismatic", "a", "c", "1 0 0")
        + joint.format("j4", "revolute", "b", "e", "0.6 0 0.8") + "</robot>")
    rng = np.random.default_rng(0)
    for robot in (industrial6, load_robot(tmp_path / "cart.yaml"),
                  load_robot(tmp_path / "tree.urdf")):
        r0s, p0s, axes, revolute, parents, _, _ = robot_arrays(robot)
        n = robot.n
        params = model_params(robot.model) * rng.uniform(0.5, 2.0)
        params[0::10] += 1.0  # the cart's links carry no inertials of their own
        model = robot.model.copy()
        for j in range(n):
            model.inertias[j + 1] = pin.Inertia.FromDynamicParameters(params[10 * j: 10 * j + 10])
        for _ in range(3):
            q = rng.uniform(-1.5, 1.5, n)
            rot, pos, ours = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, n))
            placements(q, r0s, p0s, axes, revolute, rot, pos)
            composite_mass_matrix(axes, revolute, parents, params, rot, pos,
                                  np.empty((n, 10)), ours)
            ref = pin.crba(model, model.createData(), robot.pin_q(q[None])[0])
            ref = np.triu(ref) + np.triu(ref, 1).T
            np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


@pytest.mark.filterwarnings("ignore::robid_link.exceptions.ExcitationWarning")
def test_closed_loop_log_identifies(industrial6, tmp_path):
    """Forward dynamics with Coulomb friction: the default model fits to the noise level."""
    from robid_link.ident.data.logs import write_log_csv
    from robid_link.ident.fit.identify import identify, load_logs
    from robid_link.ident.model.effects import DEFAULT_MODEL

    traj = random_fourier(industrial6, harmonics=5, base_hz=0.1, seed=1)
    t = np.arange(0.0, 20.0, 0.001)
    truth = Truth(industrial6.nominal * 1.05, effects=({"name": "viscous", "fv": 3.0},
                                                       {"name": "coulomb", "fc": 2.0}),
                  noise_tau=0.3, mode="closed_loop")
    log = Plant(industrial6, truth).run(t, *traj.evaluate(t))
    q_ref = traj.evaluate(t)[0]
    assert np.abs(log["q"] - q_ref)[:, :3].max() < 0.005  # the controller tracks
    path = tmp_path / "cl.csv"
    write_log_csv(path, log["t"], log["q"], log["tau"])
    res = identify(industrial6, load_logs(industrial6, [path]), DEFAULT_MODEL)
    np.testing.assert_allclose(res.rmse[:3], 0.3, rtol=0.15)
    fv = {p.name: p.value for p in res.parameters}
    assert fv["fv_1"] == pytest.approx(3.0, rel=0.1) and fv["fc_2"] == pytest.approx(2.0, rel=0.1)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("effects: [{name: warp}]", "effects[0]: unknown plant effect 'warp'"),
        ("effects: [{name: viscous}]", "effects[0] (viscous): missing key 'fv'"),
        ("effects: [{name: viscous, fv: 1, fc: 2}]",
         "effects[0] (viscous): unknown key 'fc' (known: fv, joint, name)"),
        ("effects: [{name: coulomb, joint: 9, fc: 1}]",
         "effects[0].joint: expected a joint number"),
        ("effects: [{name: elasticity, k: 1, d: 0, jm: 1}]",
         "'elasticity' needs mode: closed_loop"),
        ("mode: fast", "mode: expected inverse or closed_loop"),
        ("colour: red", "unknown key 'colour' (known: controller, effects, inertials,"),
        ("effects: [[viscous]]", "effects[0]: expected a mapping, got list"),
        ("inertials: [[1, 2]]", "inertials: expected 3 rows of 10"),
        ("noise: {tau: 1, bias: 2}", "noise: unknown key 'bias' (known: q_resolution, tau)"),
        ("rate_hz: -5", "rate_hz: expected a sampling rate in [10, 100000] Hz"),
        ("effects: [{name: viscous, fv: abc}]", "effects[0].fv: expected a finite number"),
        # an empty value of the wrong type is wrong, not absent (the fuzz found `perturb: []`)
        ("perturb: []", "perturb: expected a mapping, got list"),
        ("noise: []", "noise: expected a mapping, got list"),
        ("controller: []", "controller: expected a mapping"),
        ("effects: {}", "effects: expected a list"),
    ],
)
def test_truth_file_errors_name_the_key(arm3, tmp_path, text, message):
    p = tmp_path / "truth.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_truth(p, arm3)
    assert message in str(err.value) and str(p) in str(err.value)


def test_truth_file_perturb_and_motor_side(industrial6, tmp_path):
    p = tmp_path / "t.yaml"
    p.write_text("perturb: {seed: 2, spread: 0.1}\nside: motor\nnoise: {tau: 0.0}\n"
                 "effects: [{name: coulomb, joint: 2, fc: 1.0}]\n")
    truth = load_truth(p, industrial6)
    assert not np.allclose(truth.inertials, industrial6.nominal)
    t = np.arange(0.0, 2.0, 0.01)
    q = np.tile(np.linspace(0, 0.2, t.size)[:, None], (1, 6))
    qd = np.full_like(q, 0.1)
    log = Plant(industrial6, truth).run(t, q, qd, np.zeros_like(q))
    np.testing.assert_allclose(log["q"], q @ industrial6.transmission.T)


@pytest.mark.parametrize("compiled", [False, True])
def test_a_joint_pushed_off_its_stick_slides_against_its_friction(compiled):
    """A joint about to stick whose coupled neighbour pushes it harder than its friction can
    hold slides the way it is pushed, with its friction at the bound against that motion
    (the released joint's friction once pushed it along and it stuck again, held by a force
    beyond its bound)."""
    from robid_link.fakes import plant as python_loop
    from robid_link.fakes import plant_kernel as compiled_loop

    step = (compiled_loop if compiled else python_loop)._stick_slip
    minv, h = np.array([[1.0, 0.9], [0.9, 1.0]]), 1e-3
    bound, v_free = np.array([5.0, 2.0]), np.array([-1.0, -3.8e-4])
    v = step(v_free, bound, minv, h)
    force = np.linalg.solve(minv, (v - v_free) / h)
    np.testing.assert_allclose(force, [5.0, -2.0], atol=1e-9)  # both at their bounds …
    assert v[0] < 0 < v[1]  # … each against its motion: joint 2 slides the way it is pushed
    assert v[1] == pytest.approx(-3.8e-4 + h * (0.9 * 5.0 - 2.0))
    # one that can be held sticks, with a holding force within its bound
    v = step(np.array([-1.0, -3.8e-4]), np.array([1.0, 2.0]), minv, h)
    force = np.linalg.solve(minv, (v - np.array([-1.0, -3.8e-4])) / h)
    assert v[1] == 0.0 and abs(force[1]) <= 2.0 + 1e-9
