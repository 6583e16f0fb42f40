"""Close the loop on the simulated robot: a controller with 20 % inertial errors and no
friction model follows the verification path; with the identified parameter set uploaded the
tool-path error falls at least 3×."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robid_link.exceptions import ModelError
from robid_link.fakes.plant import Plant, Truth, perturbed_inertials
from robid_link.ident.excite.excitation import trajectory_states
from robid_link.ident.excite.verify import tracking, verify_trajectory
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.fit.paramset import diff_sets, feedforward, make_parameter_set, set_sha256
from robid_link.ident.model.effects import DEFAULT_MODEL
from robid_link.ident.model.robot import Robot
from tests.conftest import simulate

pytestmark = pytest.mark.filterwarnings(
    "ignore:.*the a-priori model:robid_link.exceptions.DataWarning",
    "ignore:.*a-priori model's torque:robid_link.exceptions.DataWarning")


def _closed_loop(robot: Robot, inertials: np.ndarray) -> Plant:
    truth = Truth(inertials, effects=({"name": "viscous", "fv": 3.0},
                                      {"name": "coulomb", "fc": 2.0}),
                  noise_tau=0.2, q_resolution=2 * np.pi / 2**20, mode="closed_loop",
                  controller={"rate_hz": 1000.0, "bandwidth_hz": 8.0})
    return Plant(robot, truth)


def test_uploaded_parameters_make_the_tool_follow_the_path_better(
        industrial6: Robot, tmp_path: Path) -> None:
    real = perturbed_inertials(industrial6, seed=11, spread=0.2)  # CAD is 20 % off
    log = simulate(industrial6, tmp_path / "id.csv", duration=40.0, rate=250.0, noise=0.3,
                   effects=({"name": "viscous", "fv": 3.0}, {"name": "coulomb", "fc": 2.0}),
                   seed=3, inertials=real)
    res = identify(industrial6, load_logs(industrial6, [log.path]), DEFAULT_MODEL)
    pset = make_parameter_set(industrial6, res.to_dict(), run_id="run1")
    assert pset["sha256"] == set_sha256(pset)
    ff = feedforward(pset, industrial6.n)
    path = verify_trajectory(industrial6)
    t, q, qd, qdd = trajectory_states(path, 1000.0)
    plant = _closed_loop(industrial6, real)
    before = tracking(industrial6, path, t, plant.run(t, q, qd, qdd, seed=1)["q"])
    after = tracking(industrial6, path, t, plant.run(t, q, qd, qdd, seed=1,
                                                     feedforward=ff)["q"])
    ratio = before.tool_rms_mm / after.tool_rms_mm
    print(f"tool RMS {before.tool_rms_mm:.3f} → {after.tool_rms_mm:.3f} mm ({ratio:.1f}×), "
          f"max {before.tool_max_mm:.3f} → {after.tool_max_mm:.3f} mm")
    assert ratio >= 3.0
    assert after.tool_max_mm < before.tool_max_mm


def test_a_damaged_or_foreign_parameter_set_is_refused(industrial6: Robot,
                                                       tmp_path: Path) -> None:
    log = simulate(industrial6, tmp_path / "id.csv", duration=20.0, rate=250.0, seed=4,
                   inertials=industrial6.nominal)
    doc = make_parameter_set(industrial6, identify(
        industrial6, load_logs(industrial6, [log.path]), DEFAULT_MODEL).to_dict(), run_id="r")
    bad = {**doc, "friction": {**doc["friction"], "viscous": [9.0] * 6}}
    with pytest.raises(ModelError, match=r"damaged \(sha256 mismatch\)"):
        feedforward(bad, 6)
    with pytest.raises(ModelError, match="do not fit a 3-joint robot"):
        feedforward(doc, 3)
    other = {**doc, "base_parameters": [{**p, "value": p["value"] * 1.1}
                                        for p in doc["base_parameters"]]}
    lines = diff_sets(doc, other)
    assert len(lines) == len(doc["base_parameters"]) and "+10.0 %" in lines[0]


def test_verification_path_is_fixed_and_within_limits(industrial6: Robot) -> None:
    a, b = verify_trajectory(industrial6), verify_trajectory(industrial6)
    np.testing.assert_array_equal(a.q, b.q)
    qd, _ = a.derivatives()
    assert np.all(np.abs(qd).max(axis=0) <= industrial6.limits.qd_max)
    assert np.allclose(a.q[-1], a.q[-20])  # ends at rest
