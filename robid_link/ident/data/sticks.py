"""Where a joint sticks: friction at rest is static — anywhere within ±Fc, set by whatever else
acts — so no velocity law of friction describes the rows where a joint rests at its reversals
(a closed loop without friction compensation waits there until its error has built up the
breakaway torque). Those rows are found in the raw positions and left out of that joint's
equation (``Prepared.tau_mask``); what they hold, the log cannot tell. Where the filtered
velocity touches zero — changes sign and back within one period of the cutoff, as a joint that
slows to a halt and goes on (a motion's rest point, a closed loop's brief stick) — the filter
cannot resolve the sign of a speed that small, and the model's Coulomb friction would switch
there and back; the joint keeps the sign of its motion on both sides (``Prepared.qd_sign``)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace

import numpy as np

from robid_link.ident.data.preprocess import Prepared, Problem, typical_speeds
from robid_link.ident.data.quantiles import median_of_blocks
from robid_link.ident.model.threads import in_slots

__all__ = ["Sticks", "find_sticks", "find_touches", "without_sticks", "sticks_note",
           "touches_note", "smear_rows", "STILL_WINDOW_S", "STICK_FACTOR", "STICK_SHARE_MIN",
           "DWELL_FACTOR"]

#: half-width of the window a joint's raw speed is read over (s)
STILL_WINDOW_S = 0.005
#: a still run longer than this multiple of its speed's climb out of it is a stick
STICK_FACTOR = 1.5
#: a joint sticks when its sticks hold at least this share of its samples
STICK_SHARE_MIN = 0.002
#: a reading held this many times longer than a smooth turn could hold it is a rest
DWELL_FACTOR = 2.0



@dataclass(frozen=True)
class Sticks:
    """Where one joint sticks in the training logs: the share of samples in sticks, the longest
    stick (s), how many, and the speed under which the filtered velocity smears them."""

    joint: int  # from 0
    share: float
    longest_s: float
    count: int
    speed: float


def smear_rows(prep: Prepared) -> int:
    """Rows left out on each side of a stick: one period of the cutoff, over which the filtered
    states smear it."""
    return max(1, int(round(prep.filt.fs / prep.filt.cutoff_hz)))


def _diff_scale(x: np.ndarray) -> float:
    """Robust scale of white noise on x (one joint) from its third differences (as the
    torque noise), differenced a block at a time (np.diff's numbers; no (N,) array)."""
    if x.shape[0] < 8:
        return 0.0
    m = x.shape[0] - 3

    def blocks() -> Iterator[np.ndarray]:
        for a in range(0, m, 1 << 16):
            yield np.abs(np.diff(x[a: min(m, a + (1 << 16)) + 3], 3))

    return float(1.4826 * median_of_blocks(blocks) / math.sqrt(20.0))


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
    still = q[1:] == q[:-1]
    # a rest is two equal steps in a row at least: positions that are not quantized (or a
    # fine encoder that never halts) have none, and the log's pass ends here
    if not np.any(still[1:] & still[:-1]):
        return []
    moving = still.size - int(np.count_nonzero(still))
    if moving < 10:
        return []
    step = np.diff(q)  # the encoder's count (positions that are not quantized: tiny)
    eps = float(np.min(np.abs(step, out=step), where=~still, initial=np.inf))
    del step
    out = []
    for a, b in _runs(still):
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
    acceleration could keep it). The filtered states smear it over one period of the cutoff on
    each side, so those rows go too. Joint by joint (in ``in_slots``): a long
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
    """(rows × joints: where the filtered velocity touches zero, the sign of the joint's motion
    on both sides, 0 elsewhere (int8); per joint how many touches). A touch is a run of sign
    changes of the filtered velocity, each within one period of the cutoff of the next, that
    ends on the sign it started from; runs that reach a segment's edge (the motion's start or
    end) are not touches. The velocity's signs: one byte a row and joint, most often kept by
    the typical speeds' read (``Prepared.velocity_signs``)."""
    period = max(1, int(round(prep.filt.fs / prep.filt.cutoff_hz)))
    n = prep.log.q.shape[1]
    out = np.zeros(prep.log.q.shape, np.int8)
    counts = [0] * n
    signs = prep.velocity_signs()
    for seg in prep.log.segments:
        if seg.stop - seg.start < 3 * prep.filt.settle:
            continue
        sign = signs[seg]
        for j in range(n):
            sj = sign[:, j]
            changes = np.flatnonzero(sj[1:] != sj[:-1])
            if changes.size < 2:
                continue
            for run in np.split(changes, np.flatnonzero(np.diff(changes) >= period) + 1):
                a, b = int(run[0]), int(run[-1]) + 1
                if a < period or b > sj.shape[0] - period or sj[a] == 0 or sj[b] != sj[a]:
                    continue
                out[seg.start + a: seg.start + b + 1, j] = sj[a]
                counts[j] += 1
    return out, counts


def without_sticks(pb: Problem) -> tuple[Problem, list[Sticks]]:
    """The problem with each sticking joint's stick rows left out of its equation and each
    touch of zero speed given the sign of the motion around it (training and validation logs
    alike), a note for each; the sticks found in the training logs."""
    if not any(b > a for p in pb.preps for a, b in p.filtered_segments):
        return pb, []
    # over every training log's filtered rows (one log's: found with its motion span)
    typical = pb.preps[0].typical_speed() if len(pb.preps) == 1 else typical_speeds(pb.preps)
    found = [(p, *find_sticks(p, typical), *find_touches(p)) for p in (*pb.preps, *pb.vpreps)]
    train = found[: len(pb.preps)]
    total = sum(len(p.log) for p in pb.preps)
    sticks = []
    for j in range(pb.robot.n):
        durs = [d for _, _, ds, _, _ in train for d in ds[j]]
        rows = sum(float(m[:, j].sum()) for _, m, _, _, _ in train)
        if not durs or rows / total < STICK_SHARE_MIN:
            continue
        zone = np.concatenate([p.speeds_at(m[:, j], j) for p, m, _, _, _ in train])
        sticks.append(Sticks(j, rows / total, max(durs), len(durs),
                             float(np.percentile(zone, 95))))
    touches = [sum(tc[j] for *_, tc in train) for j in range(pb.robot.n)]
    if not sticks and not any(touches):
        return pb, []

    def fixed(prep: Prepared, stuck: np.ndarray, sign: np.ndarray) -> Prepared:
        keep = (np.ones(prep.log.q.shape, bool) if prep.tau_mask is None
                else prep.tau_mask.copy())
        for st in sticks:
            keep[:, st.joint] &= ~stuck[:, st.joint]
        return replace(prep, tau_mask=keep if sticks else prep.tau_mask,
                       qd_sign=sign if sign.any() else prep.qd_sign)

    preps = [fixed(p, m, sg) for p, m, _, sg, _ in found]
    notes = ([sticks_note(sticks, pb.preps[0])] if sticks else []) + touches_note(touches,
                                                                                  pb.preps[0])
    return pb.with_preps(preps[: len(pb.preps)], preps[len(pb.preps):], notes), sticks


def sticks_note(sticks: Sequence[Sticks], prep: Prepared) -> str:
    parts = [f"joint {s.joint + 1} ({s.count} rests up to {s.longest_s:.3g} s; "
             f"{100 * s.share:.3g} % of the samples left out, speeds under {s.speed:.3g})"
             for s in sticks]
    return ("rests within the motion (sticks at reversals, pauses): " + ", ".join(parts)
            + ": friction at rest is static, so the rests and their smear by one period of the "
            f"{prep.filt.cutoff_hz:.3g} Hz cutoff are left out of the joint's equation")


def touches_note(touches: Sequence[int], prep: Prepared) -> list[str]:
    """The touches of zero speed per joint (training logs), if any."""
    parts = [f"joint {j + 1} ({k})" for j, k in enumerate(touches) if k]
    if not parts:
        return []
    return ["touches of zero speed: " + ", ".join(parts) + ": the filtered velocity changes sign "
            f"and back within one period of the {prep.filt.cutoff_hz:.3g} Hz cutoff, faster "
            "than the filter resolves; the joint keeps the sign of its motion on both sides "
            "there (its friction does not switch)"]
