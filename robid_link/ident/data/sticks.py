"""Where a joint sticks: friction at rest is static — anywhere within ±Fc, set by whatever else
acts — so no velocity law of friction describes the rows where a joint rests at its reversals
(a closed loop without friction compensation waits there until its error has built up the
breakaway torque). Those rows are found in the raw positions and left out of that joint's
equation (``Prepared.tau_mask``); what they hold, the log cannot tell. So are the rows where the
filtered velocity touches zero — changes sign and back within one period of the cutoff, as a
joint that slows to a halt and goes on (a motion's rest point, a closed loop's brief stick):
the log cannot tell whether it turned, rested or went on, so its friction's sign is unknown."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from robid_link.ident.data.preprocess import CHUNK, Prepared, Problem, typical_speeds
from robid_link.ident.model.threads import in_slots

__all__ = ["Sticks", "find_sticks", "find_touches", "without_sticks", "sticks_note",
           "smear_rows", "STILL_WINDOW_S", "STICK_FACTOR", "STICK_SHARE_MIN", "SMEAR_PERIODS",
           "DWELL_FACTOR"]

#: half-width of the window a joint's raw speed is read over (s)
STILL_WINDOW_S = 0.005
#: a still run longer than this multiple of its speed's climb out of it is a stick
STICK_FACTOR = 1.5
#: a joint sticks when its sticks hold at least this share of its samples
STICK_SHARE_MIN = 0.002
#: a reading held this many times longer than a smooth turn could hold it is a rest
DWELL_FACTOR = 2.0
#: rows left out on each side of a stick or a touch, in periods of the cutoff: the filtered
#: states smear it over about one, the parallel-filtered torque's ringing reaches further (the
#: zero-phase filter's response is still 4 % of its peak 1.25 periods on, under 1 % from 1.5)
SMEAR_PERIODS = 1.5



@dataclass(frozen=True)
class Sticks:
    """Where one joint sticks in the training logs: the share of samples in sticks, the longest
    stick (s), how many, the speed under which the filtered velocity smears them, and how many
    times the filtered velocity touches zero (left out alike)."""

    joint: int  # from 0
    share: float
    longest_s: float
    count: int
    speed: float
    touches: int = 0


def smear_rows(prep: Prepared) -> int:
    """Rows left out on each side of a stick or a touch (SMEAR_PERIODS of the cutoff)."""
    return max(1, int(round(SMEAR_PERIODS * prep.filt.fs / prep.filt.cutoff_hz)))


def _diff_scale(x: np.ndarray) -> float:
    """Robust scale of white noise on x (one joint) from its third differences (as the
    torque noise), differenced a block at a time (np.diff's numbers, one (N,) array)."""
    if x.shape[0] < 8:
        return 0.0
    d = np.empty(x.shape[0] - 3)
    for a in range(0, d.shape[0], 1 << 16):
        b = min(d.shape[0], a + (1 << 16))
        np.abs(np.diff(x[a: b + 3], 3), out=d[a:b])
    return float(1.4826 * np.median(d, overwrite_input=True) / math.sqrt(20.0))


def _climb(speed: np.ndarray, level: float) -> float:
    """Samples until ``speed`` (leaving a still run) first reaches ``level``; inf if never.
    Read in growing blocks: the climb is short, the rest of the log long."""
    at, size = 0, 64
    while at < speed.shape[0]:
        above = np.flatnonzero(speed[at: at + size] >= level)
        if above.size:
            return float(at + above[0] + 1)
        at += size
        size *= 4
    return math.inf


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(),
                    strict=True))


def _dwells(q: np.ndarray, accel_at: Callable[[int], float], dt: float
            ) -> list[tuple[int, int]]:
    """Runs [a, b) where a quantized position reads the same value longer than a smooth turn
    could: a turn at acceleration a stays within one count ε of its extremum for at most
    2·√(2ε/a); a run over DWELL_FACTOR times that (and two samples more) rests."""
    step = np.abs(np.diff(q))
    moving = step[step > 0]
    if moving.size < 10:
        return []
    eps = float(moving.min())  # the encoder's count (positions that are not quantized: tiny)
    out = []
    for a, b in _runs(step == 0):
        b += 1  # the run's last reading
        if b - a <= 2:  # within two samples of a smooth turn whatever its acceleration
            continue
        accel = abs(accel_at((a + b) // 2))
        smooth = 2.0 * math.sqrt(2.0 * eps / accel) if accel > 0 else math.inf
        if (b - a) * dt > DWELL_FACTOR * smooth + 2 * dt:
            out.append((a, b))
    return out


def find_sticks(prep: Prepared, typical: np.ndarray) -> tuple[np.ndarray, list[list[float]]]:
    """(rows × joints that stick, widened by the filter's smear; per joint the durations (s) of
    its sticks). ``typical``: each joint's 95th-percentile speed over the logs.

    A still run is where the raw position's speed over ±STILL_WINDOW_S stays under v_still
    (what its noise and 0.2 % of the typical speed allow). A joint that sticks rests there and
    leaves at once: its speed climbs from v_still to 10·v_still in a small part of the rest's
    length. A smooth passage through zero speed climbs as slowly as it fell (a reversal at
    constant q̈ spends a quarter of the climb's time under v_still; a rest-to-rest motion's
    flat turn about as long as its climb). A run longer than STICK_FACTOR times the faster of
    its two climbs, with motion on both sides, is a stick. So is a shorter rest that a fine
    encoder shows (``_dwells``: the same reading for longer than a smooth turn at the filtered
    acceleration could keep it). The filtered states and torque smear it over SMEAR_PERIODS of
    the cutoff on each side, so those rows go too. Joint by joint (in ``in_slots``): a long
    log's temporaries are one joint's column."""
    fs = prep.filt.fs
    dt = 1.0 / fs
    w = max(1, int(round(STILL_WINDOW_S * fs)))
    smear = smear_rows(prep)
    n = prep.log.q.shape[1]
    out = np.zeros(prep.log.q.shape, bool)
    segs = [seg for seg in prep.log.segments
            if seg.stop - seg.start >= max(3 * prep.filt.settle, 8 * w)]
    found: list[list[float]] = [[] for _ in range(len(segs) * n)]

    def work(task: int, slot: int) -> None:  # one joint of one segment
        seg, j = segs[task // n], task % n
        q = prep.log.q[seg, j]
        speed = np.zeros(q.shape[0])  # |(q[k + w] − q[k − w]) / 2w·dt|, in place
        inner = speed[w:-w]
        np.subtract(q[2 * w:], q[: -2 * w], out=inner)
        inner /= 2 * w * dt
        np.abs(inner, out=inner)
        sigma_v = _diff_scale(q) * math.sqrt(2.0) / (2 * w * dt)
        v_still = max(4.0 * sigma_v, 2e-3 * float(typical[j]))
        if not v_still > 0:
            return
        sticks = []
        for a, b in _runs(speed[w:-w] < v_still):
            a, b = a + w, b + w  # back to the segment's rows
            if a <= 2 * w or b >= q.shape[0] - 2 * w:
                continue  # at the segment's edge: a rest, not a stick
            climb = min(_climb(speed[a - 1:w:-1], 10 * v_still),
                        _climb(speed[b:q.shape[0] - w], 10 * v_still))
            if b - a >= 4 * w and b - a > STICK_FACTOR * climb:
                sticks.append((a, b))
                found[task].append((b - a) * dt)

        def accel_at(k: int) -> float:  # the filtered q̈ at the segment's row k
            return float(prep.kinematics(seg.start + k, seg.start + k + 1)[2][0, j])

        for a, b in _dwells(q, accel_at, dt):
            if 2 * w < a and b < q.shape[0] - 2 * w and not any(
                    a < y and x < b for x, y in sticks):
                sticks.append((a, b))
                found[task].append((b - a) * dt)
        for a, b in sticks:  # and the rows the filter smears them over
            out[seg.start + max(0, a - smear): seg.start + min(q.shape[0], b + smear), j] = True

    in_slots(range(len(found)), work)
    durations: list[list[float]] = [[] for _ in range(n)]
    for task, durs in enumerate(found):  # segment after segment, as the log runs
        durations[task % n] += durs
    return out, durations


def find_touches(prep: Prepared) -> tuple[np.ndarray, list[int]]:
    """(rows × joints where the filtered velocity touches zero, widened by the filters' smear;
    per joint how many touches). A touch is a run of sign changes of the filtered velocity
    each within one period of the cutoff of the next: the filter cannot resolve what the joint
    did there. Runs that reach a segment's edge are the motion's start or end, not touches.
    The velocity's signs are read window by window (one byte a row and joint)."""
    period = max(1, int(round(prep.filt.fs / prep.filt.cutoff_hz)))
    smear = smear_rows(prep)
    n = prep.log.q.shape[1]
    out = np.zeros(prep.log.q.shape, bool)
    counts = [0] * n
    for seg in prep.log.segments:
        if seg.stop - seg.start < 3 * prep.filt.settle:
            continue
        sign = np.empty((seg.stop - seg.start, n), np.int8)
        for lo in range(seg.start, seg.stop, CHUNK):
            hi = min(seg.stop, lo + CHUNK)
            sign[lo - seg.start: hi - seg.start] = np.sign(prep.kinematics(lo, hi)[1])
        for j in range(n):
            sj = sign[:, j]
            changes = np.flatnonzero(sj[1:] != sj[:-1])
            if changes.size < 2:
                continue
            runs = np.split(changes, np.flatnonzero(np.diff(changes) >= period) + 1)
            for run in runs:
                a, b = int(run[0]), int(run[-1]) + 1
                if run.size < 2 or a < period or b > sign.shape[0] - period:
                    continue
                out[seg.start + a - smear: seg.start + b + smear + 1, j] = True
                counts[j] += 1
    return out, counts


def _rests(prep: Prepared, typical: np.ndarray
           ) -> tuple[np.ndarray, list[list[float]], list[int]]:
    """Sticks and touches of one prepared log: the rows of either, the sticks' durations and
    the touches' counts per joint."""
    stuck, durations = find_sticks(prep, typical)
    touched, counts = find_touches(prep)
    return stuck | touched, durations, counts


def without_sticks(pb: Problem) -> tuple[Problem, list[Sticks]]:
    """The problem with each sticking joint's stick rows left out of its equation (training and
    validation logs alike), a note per joint; the sticks found in the training logs."""
    if not any(b > a for p in pb.preps for a, b in p.filtered_segments):
        return pb, []
    # over every training log's filtered rows (one log's: found with its motion span)
    typical = pb.preps[0].typical_speed() if len(pb.preps) == 1 else typical_speeds(pb.preps)
    found = [(p, *_rests(p, typical)) for p in (*pb.preps, *pb.vpreps)]
    train = found[: len(pb.preps)]
    total = sum(len(p.log) for p in pb.preps)
    sticks = []
    for j in range(pb.robot.n):
        durs = [d for _, _, ds, _ in train for d in ds[j]]
        touches = sum(tc[j] for _, _, _, tc in train)
        rows = sum(float(m[:, j].sum()) for _, m, _, _ in train)
        if not (durs or touches) or rows / total < STICK_SHARE_MIN:
            continue
        zone = np.concatenate([p.speeds_at(m[:, j], j) for p, m, _, _ in train])
        sticks.append(Sticks(j, rows / total, max(durs, default=0.0), len(durs),
                             float(np.percentile(zone, 95)), touches))
    if not sticks:
        return pb, []

    def masked(prep: Prepared, stuck: np.ndarray) -> Prepared:
        keep = (np.ones(prep.log.q.shape, bool) if prep.tau_mask is None
                else prep.tau_mask.copy())
        for st in sticks:
            keep[:, st.joint] &= ~stuck[:, st.joint]
        return replace(prep, tau_mask=keep)

    preps = [masked(p, m) for p, m, _, _ in found]
    return pb.with_preps(preps[: len(pb.preps)], preps[len(pb.preps):],
                         [sticks_note(sticks, pb.preps[0])]), sticks


def sticks_note(sticks: Sequence[Sticks], prep: Prepared) -> str:
    parts = []
    for s in sticks:
        what = [f"{s.count} rests up to {s.longest_s:.3g} s"] if s.count else []
        what += [f"{s.touches} touches of zero speed"] if s.touches else []
        parts.append(f"joint {s.joint + 1} ({', '.join(what)}; {100 * s.share:.3g} % of the "
                     f"samples left out, speeds under {s.speed:.3g})")
    touch = any(s.touches for s in sticks)
    return ("rests within the motion (sticks at reversals, pauses"
            + (", touches of zero speed" if touch else "") + "): " + ", ".join(parts)
            + ": friction at rest is static"
            + (" and where the filtered velocity touches zero (changes sign and back within one "
               "period of the cutoff) its sign is unknown" if touch else "")
            + f", so those rows and their smear by {SMEAR_PERIODS:g} periods of the "
            f"{prep.filt.cutoff_hz:.3g} Hz cutoff are left out of the joint's equation")
