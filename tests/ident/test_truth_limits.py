"""Case 3 of issue 21, on logs of the independent plant (tests/sims/arm.py): the log's limits.
A clean closed loop sticks at its reversals (static friction: no velocity law holds there); the
diagnosis leaves those rows out, says that the rate limits it, and suggests nothing there, at
250 Hz–4 kHz; hidden effects are still found where the log resolves them. Ripples aliased at
the joint's speeds and shifts within a sample are held back."""

from __future__ import annotations

import os
import warnings
from dataclasses import replace

import numpy as np
import pytest

from robid_link.ident.data.logs import Log
from robid_link.ident.data.preprocess import prepare
from robid_link.ident.data.sticks import find_sticks, find_touches
from robid_link.ident.diagnosis.candidates import Candidate
from robid_link.ident.diagnosis.diagnose import diagnose
from robid_link.ident.diagnosis.limits import (
    LogLimits,
    limited_candidates,
    limits_note,
    within_limits,
)
from robid_link.ident.diagnosis.verdict import Suggestion, Verdicts
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, REGISTRY, Block
from robid_link.ident.model.robot import load_robot

from ..conftest import ROBOTS
from ..sims.arm import Loop
from ..sims.cases import BASE, hidden, plant_log, quiet


def _diagnose(robot, path):
    with warnings.catch_warnings():
        quiet()
        logs = load_logs(robot, [path])
        res = identify(robot, logs, DEFAULT_MODEL)
        return diagnose(robot, logs, DEFAULT_MODEL, result=res)


def _closed(robot, tmp_path, rate, effects=BASE, duration=40.0, name="c"):
    path, _ = plant_log(robot, tmp_path / f"{name}{rate:g}.csv", effects=effects, rate_hz=rate,
                        duration_s=duration, loop=Loop(rate_hz=max(2000.0, rate)))
    return _diagnose(robot, path)


def test_clean_closed_loop_at_500_hz_suggests_nothing(arm3, tmp_path):
    """Today: missing_effect with stribeck@3, presliding@3, friction_power@3, ripple@1."""
    dg = _closed(arm3, tmp_path, 500.0, duration=20.0)
    assert dg.suggestions == [], dg.summary()
    assert dg.verdict in ("adequate", "doubtful")
    assert any(n.startswith("the rate limits the diagnosis") and "stick" in n
               for n in dg.notes), dg.notes
    assert any("rests within the motion" in n for n in dg.result.notes)


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
@pytest.mark.parametrize("rate", [250.0, 500.0, 1000.0, 4000.0])
@pytest.mark.parametrize("robot_name", ["arm3", "industrial6"])
def test_clean_closed_loop_no_false_suggestion(tmp_path, robot_name, rate):
    dg = _closed(load_robot(ROBOTS / f"{robot_name}.yaml"), tmp_path, rate)
    print(f"{robot_name} {rate:g} Hz: {dg.verdict}, doubts {len(dg.doubts)}")
    assert dg.suggestions == [], dg.summary()


@pytest.mark.parametrize(("name", "joint", "extra"), [("ripple", 1, {})])
def test_hidden_effect_found_in_closed_loop(arm3, tmp_path, name, joint, extra):
    dg = _closed(arm3, tmp_path, 500.0, effects=(*BASE, hidden(name, joint, **extra)),
                 duration=20.0, name=name)
    top = dg.suggestions[0]
    assert (top.effect, top.joint) == (name, joint), dg.summary()


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
@pytest.mark.parametrize("rate", [250.0, 1000.0])
@pytest.mark.parametrize(("name", "joint", "extra"), [
    ("ripple", 1, {}), ("offset", 3, {}), ("spring", 2, {}),
    ("stribeck", 2, {"vs": 0.3}),  # a transition above the speeds the sticks smear
])
def test_hidden_effects_found_in_closed_loop_matrix(arm3, tmp_path, name, joint, extra, rate):
    dg = _closed(arm3, tmp_path, rate, effects=(*BASE, hidden(name, joint, **extra)), name=name)
    top = dg.suggestions[0]
    assert (top.effect, top.joint) == (name, joint), dg.summary()


# -- the steps alone


def _prep(q: np.ndarray, fs: float = 500.0):
    t = np.arange(q.shape[0]) / fs
    log = Log("x.csv", t, q[:, None], np.zeros((t.size, 1)), segments=[slice(0, t.size)])
    return prepare(log, None)


def test_sticks_are_found_and_smooth_turns_are_not():
    fs = 500.0
    t = np.arange(0, 20, 1 / fs)
    smooth = 0.5 * np.sin(2 * np.pi * 0.3 * t)  # reversals at constant q̈
    flat = 0.3 * np.sin(2 * np.pi * 0.2 * t) ** 3  # pauses with q̇ ∝ t² (rest to rest)
    stuck = smooth.copy()
    for k in np.flatnonzero(np.abs(np.diff(np.sign(np.cos(2 * np.pi * 0.3 * t)))) > 0):
        stuck[k: k + 60] = stuck[k]  # 120 ms at rest at each reversal
    for q, n_expected in ((smooth, 0), (flat, 0), (stuck, 12)):
        prep = _prep(q, fs)
        mask, durations = find_sticks(prep, np.array([np.percentile(np.abs(prep.qd), 95)]))
        assert len(durations[0]) == n_expected, (n_expected, durations[0])
        if n_expected:
            assert min(durations[0]) > 0.08 and mask[:, 0].mean() > 0.05


def test_touches_of_zero_speed_are_found_and_smooth_turns_are_not():
    """A velocity that dips under zero and back within one period of the cutoff touches zero
    (the filter cannot resolve a speed that small): the joint keeps the sign it has on both
    sides; a turn, a long dip and the log's start at rest are no touches."""
    fs, w = 500.0, 2 * np.pi * 0.2
    t = np.arange(0, 20, 1 / fs)

    def path(eps: float) -> np.ndarray:  # q̇ = 0.2 (1 + sin ωt) − eps: under zero near the dips
        return 0.2 * (t - np.cos(w * t) / w) - eps * t

    for q, touches in ((path(2e-4), 4), (path(1e-2), 0), (0.5 * np.sin(w * t), 0)):
        prep = _prep(q, fs)
        sign, counts = find_touches(prep)
        assert counts == [touches], (touches, counts)
        assert set(np.unique(sign)) <= {0, 1}  # q̇ > 0 on both sides of each dip
        if touches:  # the dips' rows, a few tens of ms each
            assert 0.003 < (sign != 0).mean() < 0.03
            fixed = replace(prep, qd_sign=sign).qd[:, 0]
            assert (fixed[sign[:, 0] != 0] > 0).all() and (fixed[sign[:, 0] == 0] ==
                                                           prep.qd[sign[:, 0] == 0, 0]).all()
    start = np.where(t < 1.0, 0.0, 0.3 * (1 - np.cos(w * (t - 1.0))))  # at rest, then moving
    assert find_touches(_prep(start, fs))[1] == [0]


def _sug(effect, joint, **fields):
    return Suggestion(effect, joint, [0.1], 0.3, 1e-6, "", {"rmse_after": 0.1, **fields})


def test_aliased_ripple_and_a_sub_sample_shift_are_held_back():
    limits = LogLimits(250.0, 10.0, np.array([1.5, 1.0]), {})
    fine = Candidate(Block(REGISTRY["ripple"], 0, {"period": 0.01}), [0, 1])  # 150 Hz
    slow = Candidate(Block(REGISTRY["ripple"], 1, {"period": 0.1}), [0, 1])  # 10 Hz
    limited = limited_candidates([fine, slow], limits)
    assert list(limited) == ["ripple@1"] and "Nyquist" in limited["ripple@1"][0]
    v = Verdicts([_sug("ripple", 1), _sug("ripple", 2), _sug("delay", None, seconds=0.0015),
                  _sug("delay", None, seconds=0.01)], [], [])
    kept, held = within_limits(v, limited, 250.0)
    assert [s.label() for s in kept.suggested] == ["ripple@2", "delay"]
    assert list(held) == ["ripple@1", "delay"] and held["delay"][0].fields["seconds"] == 0.0015
    note = limits_note(limits, held)[0]
    assert note.startswith("the rate limits the diagnosis") and "sample-and-hold" in note


def test_limits_note_names_the_speeds_left_out():
    note = limits_note(LogLimits(500.0, 10.0, np.ones(3), {2: 0.335}), {})[0]
    assert "joint(s) 3 stick" in note and "0.335" in note and "500 Hz" in note
    assert limits_note(LogLimits(500.0, 10.0, np.ones(3), {}), {}) == []
