"""Case 6 of issue 21, on logs of the independent plant (tests/sims/arm.py): a gas-spring
counterbalance the model lacks is suggested as a spring whose suggestion points to
``known_torque`` with the law filled in for that joint, and that entry, identified, removes
the error the strut caused; a ripple (cogging) gets no such pointer."""

from __future__ import annotations

import os
import warnings

import pytest

from robid_link.ident.diagnosis.diagnose import diagnose
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, Model
from robid_link.ident.model.known import parse_known_torques
from robid_link.ident.model.robot import load_robot

from ..conftest import ROBOTS
from ..sims.arm import Effect
from ..sims.cases import BASE, hidden, plant_log, quiet

#: a gas strut on joint 2 (polytropic, not the linear spring law the pointer offers)
GAS = Effect("gas_spring", 2, {"f0": 6.0, "g": 0.4, "kappa": 1.3, "a": 0.12, "b": 0.3,
                               "phi": 0.6})


def _diagnose(robot, path):
    with warnings.catch_warnings():
        quiet()
        logs = load_logs(robot, [path])
        return logs, diagnose(robot, logs, DEFAULT_MODEL)


def _removed(robot, logs, clean, entry, joint: int) -> float:
    """The share of the strut's excess error that ``entry``, identified with the model, removes
    (against the same plant's log without the strut)."""
    model = Model(DEFAULT_MODEL.specs, parse_known_torques([entry], "known_torque"))
    with warnings.catch_warnings():
        quiet()
        before = identify(robot, logs, DEFAULT_MODEL).rmse[joint - 1]
        after = identify(robot, logs, model).rmse[joint - 1]
        ref = identify(robot, load_logs(robot, [clean]), DEFAULT_MODEL).rmse[joint - 1]
    return 1 - (after**2 - ref**2) / (before**2 - ref**2)


def _strut_case(robot, tmp_path, joint: int, gas: Effect = GAS, seed: int = 1
                ) -> tuple[float, float | None]:
    """The share of the strut's excess error the suggested entry removes; and when the note
    says the log does not fix the strut's shape, the share the entry removes with the strut's
    measured a, b and φ (what the note asks the user for), else None."""
    gas = Effect(gas.name, joint, gas.p)
    hp, _ = plant_log(robot, tmp_path / "g.csv", effects=(*BASE, gas), duration_s=30.0,
                      seed=seed)
    cp, _ = plant_log(robot, tmp_path / "c.csv", duration_s=30.0, seed=seed)
    logs, dg = _diagnose(robot, hp)
    top = dg.suggestions[0]
    assert (top.effect, top.joint) == ("spring", joint), dg.summary()
    entry = top.known_torque
    assert entry is not None and entry["joint"] == joint and entry["identify"] == ["f0", "f1", "f2"]
    assert top.as_dict()["known_torque"] == entry
    assert "known_torque" in top.evidence
    note = next(n for n in dg.notes
                if n.startswith(f"spring@{joint}: joint {joint}'s residual follows"))
    assert f"counterbalance{joint}" in note and "\n" not in note
    # the filled-in entry, identified with the model, takes the strut's error away
    removed = _removed(robot, logs, cp, entry, joint)
    if "does not fix the strut's shape" not in note:
        return removed, None
    measured = {**entry, "constants": {k: gas.p[k] for k in ("a", "b", "phi")}}
    return removed, _removed(robot, logs, cp, measured, joint)


def test_gas_spring_points_to_known_torque(arm3, tmp_path):
    removed, _ = _strut_case(arm3, tmp_path, 2)
    print(f"gas strut on joint 2: {100 * removed:.1f} % of the excess removed by the entry")
    assert removed >= 0.9, f"{100 * removed:.1f} % of the excess removed"


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
@pytest.mark.parametrize("robot_name,joint", [("arm3", 2), ("arm3", 3), ("industrial6", 2),
                                              ("industrial6", 3)])
def test_strut_matrix(tmp_path, robot_name, joint):
    """The suggested entry removes the strut's error, or the note says the log does not fix
    the strut's shape and the entry with the strut's measured a, b, φ removes it. Measured: on
    industrial6 the joint's gravity parameters take most of the strut's torque (a sine of the
    angle), what is left fixes no shape (the suggested entry alone removes 7–86 %), and the
    note says so."""
    robot = load_robot(ROBOTS / f"{robot_name}.yaml")
    got = {s: _strut_case(robot, tmp_path, joint, seed=s) for s in (1, 2)}
    print(f"{robot_name} joint {joint}: " + ", ".join(
        f"seed {s} {100 * v:.1f} %" + ("" if m is None else f" (measured shape {100 * m:.1f} %)")
        for s, (v, m) in got.items()))
    assert all((m if m is not None else v) >= 0.9 for v, m in got.values())


def test_cogging_gets_no_counterbalance_pointer(arm3, tmp_path):
    hp, _ = plant_log(arm3, tmp_path / "r.csv", effects=(*BASE, hidden("ripple", 2)),
                      duration_s=30.0)
    _, dg = _diagnose(arm3, hp)
    assert dg.suggestions and dg.suggestions[0].effect == "ripple", dg.summary()
    assert all(s.known_torque is None for s in dg.suggestions)
    assert not any("counterbalance" in n for n in dg.notes)


@pytest.mark.parametrize("ratio,phi", [(0.4, 0.6), (0.2, -1.0)])
def test_entry_is_a_valid_known_torque(ratio, phi):
    from robid_link.ident.diagnosis.evidence import known_torque_entry

    (kt,) = parse_known_torques([known_torque_entry(3, ratio, phi)], "known_torque")
    assert kt.joint == 3 and kt.identify == ("f0", "f1", "f2")
    assert dict(kt.constants) == {"a": ratio, "b": 1.0, "phi": phi}
