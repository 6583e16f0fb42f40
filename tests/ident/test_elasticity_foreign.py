"""Elasticity on logs of a plant the analysis was not written against (tests/sims/twomass.py, which
imports neither fakes/ nor the analysis): PD, PI-velocity and cascaded loops, with and without a
drift and arm friction, 1–4 kHz, two noise levels, a coupled pair. Jm, Ja, K within 1 % and D
within 2 % of the truth, with the schedule and from the log alone; the notes (arm friction, a
second resonance) appear when the plant has the effect and not when it does not.

The quick cases run in ``make test``; the whole matrix with ``make validate``
(``ROBID_VALIDATE=1 pytest -s -m slow tests/ident/test_elasticity_foreign.py`` prints the errors).
"""

from __future__ import annotations

import itertools
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from robid_link.ident.data.logs import load_log
from robid_link.ident.elastic.elasticity import ElasticityResult, identify_elasticity
from robid_link.ident.model.robot import load_robot
from tests.sims.twomass import Axis, Loop, Noise, Run, SteppedSine, robot_yaml, simulate

# antiresonance 9.5 Hz, resonance 19 Hz; the arm's viscous friction Ba is fitted too
BIG = Axis(jm=0.8, ja=2.5, k=9000.0, d=6.0, ba=1.5)
#: arm Coulomb friction: half the torque amplitude of the lowest step; without a drift the arm
#: sticks for part of each period up to ~6 Hz (the describing function is off by 8 % there)
FRICTION = 1.0
NOISE = {"low": Noise(tau=0.02, disturbance=0.02, q_step=3e-7),
         "high": Noise(tau=0.2, disturbance=0.2, q_step=3e-7)}
EXCITE = SteppedSine(steps=18)  # 2–60 Hz, ≥ 1 s settled (the drift's reversal rings the arm)
QUICK = {"steps": 14}  # make test: fewer steps, ~40 s of log
DRIFT = 0.15  # rad/s: three times the sine's velocity amplitude (0.05)


def _loop(kind: str, rate_hz: float) -> Loop:
    """PD and PI-velocity at the log's rate (the torque held over each logged sample); the
    cascade at 4 kHz with a 0.3 ms current loop (the logged torque is the lagged one)."""
    if kind == "cascade":
        return Loop("cascade", rate_hz=4000.0, torque_lag_s=3e-4)
    return Loop(kind, rate_hz=rate_hz)


def _simulate(kind: str, drift: bool, friction: bool, rate_hz: float, noise: str,
              axis: Axis = BIG, seed: int = 1, **exc: float) -> Run:
    ax = Axis(**{**axis.__dict__, "fc_arm": FRICTION if friction else 0.0})
    excite = SteppedSine(**{**EXCITE.__dict__, "drift": DRIFT if drift else 0.0, **exc})
    return simulate([ax], _loop(kind, rate_hz), excite, log_rate_hz=rate_hz,
                    noise=NOISE[noise], seed=seed)


def _identify(run: Run, tmp: Path, *, schedule: bool, axes: list[Axis] | None = None
              ) -> ElasticityResult:
    """Through the house CSV, the log loader and a robot description, as a user would."""
    csv, _ = run.write(tmp)
    n = run.q.shape[1]
    axes = axes or [Axis(**{k: run.truth[j + 1][k] for k in ("jm", "ja", "k", "d", "kg")})
                    for j in range(n)]
    (tmp / "robot.yaml").write_text(robot_yaml("twomass", axes, run.pose))
    robot = load_robot(tmp / "robot.yaml")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the loader's notes on a log it resamples
        log = load_log(csv, n)
    return identify_elasticity(robot, [log], joints=[1] if n == 1 else (),
                               pair=(1, 2) if n == 2 else None,
                               schedule=run.schedule if schedule else None)


def _errors(res: ElasticityResult, run: Run) -> dict[int, dict[str, float]]:
    return {p.joint: {n: 100 * (getattr(p, n) / run.truth[p.joint][n] - 1)
                      for n in ("jm", "ja", "k", "d")} for p in res.joints}


def _check(res: ElasticityResult, run: Run, label: str) -> None:
    for joint, err in _errors(res, run).items():
        print(f"{label} joint {joint}: " + " ".join(f"{n} {e:+.2f}%" for n, e in err.items()))
        for name in ("jm", "ja", "k"):
            assert abs(err[name]) < 1.0, (label, joint, name, err)
        assert abs(err["d"]) < 2.0, (label, joint, "d", err)
    for p in res.joints:  # physical by construction, not clipped
        assert p.jm > 0 and p.ja > 0 and p.k > 0 and p.d > 0 and p.ba >= 0
        assert p.fc is None or p.fc >= 0


def _notes(res: ElasticityResult, what: str) -> list[str]:
    return [n for n in res.notes if what in n]


# ----------------------------------------------------------------------------- make test


def test_pd_loop_without_drift_is_unbiased(tmp_path):
    """The issue's log: a PD position loop, no drift, no arm friction, 2 kHz, the high noise.
    D came out +11 % (the torque held over each sample lags it half a sample: now fitted),
    with a note of arm friction and of a second resonance; now neither."""
    run = _simulate("pd", drift=False, friction=False, rate_hz=2000.0, noise="high", **QUICK)
    for schedule in (True, False):
        res = _identify(run, tmp_path, schedule=schedule)
        _check(res, run, "schedule" if schedule else "log alone")
        p = res.joints[0]
        # the torque acts half a sample after it is logged: held (hold/2) or delayed
        assert p.hold_s / 2 + p.delay_s == pytest.approx(0.25e-3, abs=2e-5)
        assert not _notes(res, "friction") and not _notes(res, "second resonance")
        assert res.frfs[0].f_hz.size == QUICK["steps"]  # every step found, none dropped
        assert p.tests["arm_coulomb"]["p"] > 1e-3 and not p.tests["third_mass"]["kept"]


def test_cascade_with_drift_and_arm_friction(tmp_path):
    """A cascade (current loop lag, 4 kHz) logged at 1 kHz, drifting, arm friction: where the
    arm outruns the drift its friction shows, is named with its F-test and fitted."""
    run = _simulate("cascade", drift=True, friction=True, rate_hz=1000.0, noise="low", **QUICK)
    res = _identify(run, tmp_path, schedule=True)
    _check(res, run, "cascade")
    assert res.joints[0].hold_s == 0.0  # the lagged torque is not held


def test_arm_stick_slip_without_drift_is_named_and_fitted(tmp_path):
    """PI-velocity loop, no drift, strong arm friction: the arm sticks for part of each period
    at the low steps (the describing function is 8 % off there, D was −7 %); the stick-slip is
    integrated under the logged motor motion, the note gives F and p."""
    run = _simulate("pi_velocity", drift=False, friction=True, rate_hz=2000.0, noise="low",
                    **QUICK)
    res = _identify(run, tmp_path, schedule=True)
    _check(res, run, "stick-slip")
    [note] = _notes(res, "Coulomb friction on the arm")
    assert "F = " in note and "p = " in note and "stick-slip" in note
    assert res.joints[0].fc == pytest.approx(FRICTION, rel=0.02)
    assert not _notes(res, "second resonance")


def test_second_resonance_is_named_only_when_there(tmp_path):
    """A third mass behind the arm (a second mode near 40 Hz): named with its F-test and the
    three-mass fit's parameters kept; the same plant without it gets no such note."""
    third = Axis(**{**BIG.__dict__, "third": (0.6, 37900.0, 9.0)})
    run = _simulate("pd", drift=True, friction=False, rate_hz=2000.0, noise="low",
                    axis=third, f_max_hz=80.0, steps=20)
    res = _identify(run, tmp_path, schedule=True, axes=[BIG])
    [note] = _notes(res, "second resonance")
    assert "three-mass" in note and "F = " in note and "p = " in note
    _check(res, run, "three masses")
    j3 = res.joints[0].third
    assert j3 is not None and j3[0] == pytest.approx(0.6, rel=0.05)


# ----------------------------------------------------------------------------- make validate

MATRIX = list(itertools.product(("pd", "pi_velocity", "cascade"), (False, True), (False, True),
                                (1000.0, 2000.0, 4000.0), ("low", "high")))


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
@pytest.mark.parametrize("kind, drift, friction, rate_hz, noise", MATRIX,
                         ids=[f"{k}-{'drift' if d else 'still'}-{'fc' if f else 'nofc'}-"
                              f"{r / 1000:g}k-{n}" for k, d, f, r, n in MATRIX])
def test_matrix(tmp_path, kind, drift, friction, rate_hz, noise):
    run = _simulate(kind, drift, friction, rate_hz, noise)
    label = f"{kind} drift={drift} friction={friction} {rate_hz / 1000:g} kHz {noise}"
    for schedule in (True, False):
        res = _identify(run, tmp_path, schedule=schedule)
        _check(res, run, f"{label} {'schedule' if schedule else 'log alone'}")
        assert not _notes(res, "second resonance")
        if not friction:
            assert not _notes(res, "friction")
        elif not drift:  # the arm reverses at every step: its friction shows
            assert _notes(res, "Coulomb friction on the arm")


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
@pytest.mark.parametrize("drift", [True, False], ids=["drift", "still"])
def test_coupled_pair(tmp_path, drift):
    """Two axes whose arms share Jcop = 0.6, each excited in turn (the other drifts along):
    the 2×2 FRF's fit within the targets, Jcop within 5 %."""
    second = Axis(jm=0.25, ja=0.9, k=4000.0, d=2.0, ba=0.5)
    excite = SteppedSine(**{**EXCITE.__dict__, "drift": DRIFT if drift else 0.0})
    run = simulate([BIG, second], _loop("pd", 2000.0), excite, log_rate_hz=2000.0,
                   noise=NOISE["low"], jcop=0.6, seed=2)
    for schedule in (True, False):
        res = _identify(run, tmp_path, schedule=schedule)
        _check(res, run, f"pair drift={drift} {'schedule' if schedule else 'log alone'}")
        assert res.coupled is not None
        err = 100 * (res.coupled.jcop / 0.6 - 1)
        print(f"pair drift={drift}: Jcop {err:+.2f}%")
        assert abs(err) < 5.0
        assert np.isfinite(res.coupled.std["jcop"])
