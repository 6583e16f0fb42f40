"""Diagnosis: hide an effect from the model, find it, add it, watch the error fall."""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from robid_link.exceptions import ConditioningWarning, DataWarning
from robid_link.ident.diagnosis.diagnose import diagnose
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, EffectSpec, Model
from robid_link.ident.model.robot import load_robot

from ..conftest import ROBOTS, simulate

VISCOUS = {"name": "viscous", "fv": 2.0}
COULOMB = {"name": "coulomb", "fc": 1.5}


@dataclass(frozen=True)
class Case:
    hidden: dict
    accept: tuple[tuple[str, int | None], ...]  # acceptable top suggestions (effect, joint)
    model: tuple = ("rigid_body", "viscous", "coulomb")
    base: tuple = (VISCOUS, COULOMB)


def _only(effect: dict, joints: list[int]) -> tuple[dict, ...]:
    return tuple({**effect, "joint": j} for j in joints)


CASES = {
    "viscous": Case({"name": "viscous", "joint": 2, "fv": 3.0}, (("viscous", 2),),
                    ("rigid_body", "coulomb", "viscous@1", "viscous@3"),
                    (*_only(VISCOUS, [1, 3]), COULOMB)),
    "coulomb": Case({"name": "coulomb", "joint": 3, "fc": 2.0}, (("coulomb", 3),),
                    ("rigid_body", "viscous", "coulomb@1", "coulomb@2"),
                    (VISCOUS, *_only(COULOMB, [1, 2]))),
    "offset": Case({"name": "offset", "joint": 3, "b": 0.8}, (("offset", 3),
                                                              ("coulomb_asymmetric", 3))),
    # ≡ coulomb + offset (declared): with Coulomb in the model the simpler offset is as good
    "coulomb_asymmetric": Case({"name": "coulomb_asymmetric", "joint": 1, "fc_pos": 2.5,
                                "fc_neg": 0.5}, (("coulomb_asymmetric", 1), ("offset", 1)),
                               base=(VISCOUS, *_only(COULOMB, [2, 3]))),
    "friction_power": Case({"name": "friction_power", "joint": 2, "fc": 1.0, "fv": 4.0,
                            "alpha": 0.35}, (("friction_power", 2),),
                           base=(*_only(VISCOUS, [1, 3]), *_only(COULOMB, [1, 3]))),
    "stribeck": Case({"name": "stribeck", "joint": 2, "fs": 4.0, "fc": 1.5, "vs": 0.05},
                     (("stribeck", 2),), base=(VISCOUS, *_only(COULOMB, [1, 3]))),
    "armature": Case({"name": "armature", "joint": 3, "ia": 0.4}, (("armature", 3),)),
    # a balancing spring whose anchor passes close to the axis: far from a sine in q2
    "spring": Case({"name": "spring", "joint": 2, "k": 2000.0, "a": 0.15, "b": 0.2, "l0": 0.3,
                    "phi": 0.4}, (("spring", 2),)),
    "ripple": Case({"name": "ripple", "joint": 1, "amplitude": 0.6, "period": 0.1},
                   (("ripple", 1),)),
    "friction_drift": Case({"name": "friction_drift", "joint": 2, "fc": 1.5, "fv": 2.0,
                            "change": 1.0, "tau_s": 15.0}, (("friction_drift", 2),),
                           base=(*_only(VISCOUS, [1, 3]), *_only(COULOMB, [1, 3]))),
    "load_friction": Case({"name": "load_friction", "joint": 2, "mu": 0.08},
                          (("load_friction", 2),)),
    "delay": Case({"name": "delay", "seconds": 0.01}, (("delay", None),)),
}
FAST = ["offset", "spring", "ripple", "stribeck", "delay", "armature"]


def _parse(label: str) -> tuple[str, int | None]:
    effect, _, joint = label.partition("@")
    return effect, int(joint) if joint.isdigit() else None


def _spec(s) -> EffectSpec:
    opts = dict(s.hypers)
    if s.effect == "delay":
        opts = {"seconds": s.fields["seconds"]}
    return EffectSpec(s.effect, s.joint, tuple(sorted(opts.items())))


def _expected_warnings() -> None:
    """What simulated logs are known to raise here: weakly excited columns (a spring, a
    ripple) and a joint whose torque differs much from the a-priori model's (arm3's light
    wrist, perturbed inertials). Anything else still fails the test."""
    warnings.simplefilter("ignore", ConditioningWarning)
    warnings.filterwarnings("ignore", r".*(the a-priori model's torque|has the opposite sign of "
                            r"the a-priori model)", DataWarning)


def _run_case(robot, case: Case, tmp: Path, seed: int, duration: float = 40.0):
    model = Model.parse(list(case.model))
    kw = {"noise": 0.3, "seed": seed, "duration": duration, "rate": 250.0}
    hidden = simulate(robot, tmp / "hidden.csv", effects=(*case.base, case.hidden), **kw)
    clean = simulate(robot, tmp / "clean.csv", effects=case.base, **kw)
    with warnings.catch_warnings():
        _expected_warnings()
        logs = load_logs(robot, [hidden.path])
        dg = diagnose(robot, logs, model)
        assert dg.verdict == "missing_effect", dg.summary()
        top = dg.suggestions[0]
        # the top one or an effect it names as explaining the same (the log cannot tell them
        # apart): the excess it removes is checked below either way
        named = {(top.effect, top.joint)} | {_parse(a) for a in top.alternatives}
        assert named & set(case.accept), dg.summary()
        before = identify(robot, logs, model).rmse
        ref = identify(robot, load_logs(robot, [clean.path]), model).rmse
        after = identify(robot, logs, model.with_added(_spec(top))).rmse
    rows = [top.joint - 1] if top.joint else list(range(robot.n))
    excess = np.sum(before[rows] ** 2 - ref[rows] ** 2)
    left = np.sum(after[rows] ** 2 - ref[rows] ** 2)
    assert excess > 0
    assert left <= 0.10 * excess, f"{top.label()}: {100 * left / excess:.0f} % of the excess left"
    # every number in the evidence sentence is also a field
    for token in top.evidence.replace("(", " ").replace(")", " ").replace(";", " ").split():
        try:
            value = float(token.rstrip("%").rstrip(","))
        except ValueError:
            continue
        if token.startswith(("q", "τ")):
            continue
        assert any(np.isclose(value, v, rtol=2e-3) or np.isclose(value, 1e3 * v, rtol=2e-3)
                   for v in top.fields.values() if isinstance(v, float | int)) or \
            value in (top.joint,), (token, top.evidence, top.fields)
    return dg


@pytest.mark.parametrize("name", FAST)
def test_hidden_effect_is_found_and_removed(arm3, tmp_path, name):
    _run_case(arm3, CASES[name], tmp_path, seed=5)


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
@pytest.mark.parametrize("seed", [11, 12, 13])
@pytest.mark.parametrize("robot_name", ["arm3", "industrial6"])
@pytest.mark.parametrize("name", sorted(CASES))
def test_matrix_every_effect(tmp_path, name, robot_name, seed):
    _run_case(load_robot(ROBOTS / f"{robot_name}.yaml"), CASES[name], tmp_path, seed=seed)


@pytest.mark.parametrize("robot_name", ["arm3", "industrial6"])
def test_clean_log_is_adequate(robot_name, tmp_path):
    robot = load_robot(ROBOTS / f"{robot_name}.yaml")
    sim = simulate(robot, tmp_path / "c.csv", noise=0.3, seed=7, duration=40.0, rate=250.0)
    with warnings.catch_warnings():
        _expected_warnings()
        dg = diagnose(robot, load_logs(robot, [sim.path]), DEFAULT_MODEL)
    assert dg.verdict == "adequate", dg.summary()
    assert dg.to_dict()["suggestions"] == []
    # the same validation RMSE identify reports for these inputs
    res = identify(robot, load_logs(robot, [sim.path]), DEFAULT_MODEL)
    np.testing.assert_allclose(dg.to_dict()["rmse"], res.rmse)


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
def test_false_alarm_rate_over_clean_seeds(arm3, tmp_path):
    alarms = []
    for seed in range(20):
        sim = simulate(arm3, tmp_path / f"c{seed}.csv", noise=0.3, seed=100 + seed,
                       duration=40.0, rate=250.0)
        with warnings.catch_warnings():
            _expected_warnings()
            dg = diagnose(arm3, load_logs(arm3, [sim.path]), DEFAULT_MODEL)
        alarms.append(dg.verdict != "adequate")
    print(f"false alarms: {sum(alarms)} of 20 clean seeds")
    assert sum(alarms) <= 1


def test_two_hidden_effects_one_after_the_other(arm3, tmp_path):
    hidden = ({"name": "spring", "joint": 2, "k": 3000.0, "a": 0.1, "b": 0.3, "l0": 0.15,
               "phi": 0.4}, {"name": "offset", "joint": 3, "b": 0.8})
    sim = simulate(arm3, tmp_path / "two.csv", noise=0.3, seed=9, duration=40.0, rate=250.0,
                   effects=(VISCOUS, COULOMB, *hidden))
    model = DEFAULT_MODEL
    found = []
    with warnings.catch_warnings():
        _expected_warnings()
        logs = load_logs(arm3, [sim.path])
        for _ in range(3):
            dg = diagnose(arm3, logs, model)
            if dg.verdict == "adequate":
                break
            top = dg.suggestions[0]
            found.append((top.effect, top.joint))
            model = model.with_added(_spec(top))
    assert found[:2] == [("spring", 2), ("offset", 3)]
    assert dg.verdict == "adequate"


# -- effects written here as closed forms unlike the catalog's bases, on a robot used nowhere
SCARA = """name: scara4
joints:
  - {name: s1, alpha: 0, a: 0, theta: 0, d: 0.3, limits: {q: [-150, 150], qd: 120, qdd: 300},
     inertial: {m: 5.0, com: [0.15, 0, 0], I: [0.02, 0, 0.05, 0, 0, 0.05]}}
  - {name: s2, alpha: 90, a: 0.35, theta: 0, d: 0, limits: {q: [-80, 80], qd: 120, qdd: 300},
     inertial: {m: 3.0, com: [0.12, 0.01, 0], I: [0.01, 0, 0.03, 0, 0, 0.03]}}
  - {name: s3, alpha: -90, a: 0.3, theta: 0, d: 0, limits: {q: [-120, 120], qd: 150, qdd: 400},
     inertial: {m: 1.5, com: [0, 0.05, 0.02], I: [0.006, 0, 0.004, 0, 0, 0.005]}}
  - {name: s4, alpha: 90, a: 0, theta: 0, d: 0.12, limits: {q: [-170, 170], qd: 200, qdd: 500},
     inertial: {m: 0.6, com: [0, 0, 0.03], I: [0.001, 0, 0.001, 0, 0, 0.0008]}}
"""


@pytest.mark.parametrize(
    ("extra", "joint", "accept"),
    [
        # a gas spring whose torque is a cube of the sine of the angle
        (lambda t, q, qd: 6.0 * np.sin(q[:, 1] + 0.3) ** 3, 2, {"spring"}),
        # square-wave cogging: only its first harmonic is in the ripple basis
        (lambda t, q, qd: 0.5 * np.sign(np.sin(2 * np.pi * q[:, 0] / 0.15)), 1, {"ripple"}),
    ],
    ids=["gas_spring", "square_cogging"],
)
def test_closed_form_effects_on_an_unseen_robot(tmp_path, extra, joint, accept):
    from robid_link.fakes.plant import Plant, Truth
    from robid_link.ident.data.logs import write_log_csv
    from robid_link.ident.excite.excitation import random_fourier

    desc = tmp_path / "scara4.yaml"
    desc.write_text(SCARA)
    robot = load_robot(desc)
    traj = random_fourier(robot, harmonics=5, base_hz=0.1, seed=2)
    t = np.arange(0.0, 40.0, 1 / 250.0)
    q, qd, qdd = traj.evaluate(t)
    log = Plant(robot, Truth(robot.nominal * 1.1, effects=(VISCOUS, COULOMB), noise_tau=0.2)
                ).run(t, q, qd, qdd, seed=3)
    tau = log["tau"].copy()
    tau[:, joint - 1] += extra(t, q, qd)
    path = tmp_path / "log.csv"
    write_log_csv(path, t, log["q"], tau)
    with warnings.catch_warnings():
        _expected_warnings()
        dg = diagnose(robot, load_logs(robot, [path]), DEFAULT_MODEL)
    top = dg.suggestions[0]
    assert top.effect in accept and top.joint == joint, dg.summary()
