"""The log's limits: what its rate, the filter's cutoff and the torque log's timing let a
diagnosis separate. Rows where a joint sticks at its reversals were left out of its equation
(``data/sticks.py``): friction acting only at lower speeds cannot be seen. A ripple that turns
faster than the Nyquist frequency at the joint's speeds is aliased; a time shift within one
sample is the log's own timing (a torque held over the controller's tick acts half a sample
late: its sample-and-hold). Such candidates are not suggested, and the diagnosis
says that the rate limits it."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robid_link.ident.data.preprocess import Prepared
from robid_link.ident.diagnosis.candidates import Candidate
from robid_link.ident.diagnosis.verdict import Suggestion, Verdicts

__all__ = ["LogLimits", "log_limits", "limited_candidates", "within_limits", "within_a_sample",
           "limits_note"]

#: why a candidate or a suggestion is held back, and its figure
Reason = tuple[str, str]


@dataclass(frozen=True)
class LogLimits:
    """The training logs' rate and cutoff, each joint's 95th-percentile speed, and per joint
    (from 0) whose sticks were left out the speed under which its rows are gone."""

    fs: float
    cutoff_hz: float
    speed: np.ndarray
    unseen_below: dict[int, float]


def log_limits(preps: Sequence[Prepared]) -> LogLimits:
    """The limits of the training logs ``preps`` (the first one's rate and cutoff)."""
    n = preps[0].q.shape[1]
    speeds = np.concatenate([np.abs(p.qd) for p in preps])
    unseen: dict[int, float] = {}
    for j in range(n):
        gone = [np.abs(p.qd[~p.tau_mask[:, j], j]) for p in preps if p.tau_mask is not None
                and p.tau_mask[:, j].any() and not p.tau_mask[:, j].all()]
        if gone:
            unseen[j] = float(np.percentile(np.concatenate(gone), 95))
    return LogLimits(float(preps[0].filt.fs), float(preps[0].filt.cutoff_hz),
                     np.percentile(speeds, 95, axis=0), unseen)


def limited_candidates(kept: Sequence[Candidate], limits: LogLimits) -> dict[str, Reason]:
    """The candidates the log cannot separate, by key, each with (why, its figure): a ripple
    aliased at the joint's speeds."""
    out: dict[str, Reason] = {}
    for c in kept:
        blk = c.block
        if blk.effect.name != "ripple" or blk.joint is None:
            continue
        period = float(blk.opts.get("period", 0.0))
        turns = limits.speed[blk.joint] / max(period, 1e-12)
        if turns > limits.fs / 2:
            out[blk.key] = (f"a ripple at the joint's speeds turns faster than the log's "
                            f"Nyquist frequency {limits.fs / 2:.4g} Hz (aliased)",
                            f"period {period:.3g} rad, up to {turns:.3g} Hz")
    return out


def within_limits(v: Verdicts, limited: dict[str, Reason], fs: float
                  ) -> tuple[Verdicts, dict[str, tuple[Suggestion, Reason]]]:
    """The suggestions the log cannot separate taken out (``limited`` from
    ``limited_candidates``, and a delay within one sample: the log's own sample-and-hold),
    each with its reason; the others as they were."""
    keep, out = [], {}
    for sug in v.suggested:
        key = sug.label()
        secs = sug.fields.get("seconds")
        reason = limited.get(key)
        if sug.effect == "delay" and secs is not None and within_a_sample(secs, fs):
            reason = (f"a shift within the log's sample period ({1e3 / fs:.3g} ms) is the log's "
                      "own timing (a torque held over the controller's tick acts half a sample "
                      "late: its sample-and-hold)", f"{1e3 * secs:.3g} ms")
        if reason is not None:
            out[key] = (sug, reason)
        else:
            keep.append(sug)
    return Verdicts(keep, v.rejected, v.not_transferring), out


def within_a_sample(seconds: float, fs: float) -> bool:
    """Whether a shift of the torque log is within the log's own timing (one sample period)."""
    return abs(seconds) < 1.0 / fs


def limits_note(limits: LogLimits, held: dict[str, tuple[Suggestion, Reason]]) -> list[str]:
    """One note saying what the log cannot show: the speeds left out where joints stick, and the
    suggestions held back, grouped by why."""
    parts = []
    if limits.unseen_below:
        joints = sorted(limits.unseen_below)
        parts.append(
            f"joint(s) {', '.join(str(j + 1) for j in joints)} stick at their reversals and at "
            f"{limits.fs:.4g} Hz with a {limits.cutoff_hz:.3g} Hz cutoff their rows under "
            + ", ".join(f"{limits.unseen_below[j]:.3g}" for j in joints)
            + " rad/s (m/s) are left out: friction acting only at lower speeds (a Stribeck or "
            "pre-sliding transition under them) cannot be seen")
    groups: dict[str, list[str]] = {}
    for key, (_, (why, figure)) in held.items():
        groups.setdefault(why, []).append(f"{key} ({figure})")
    parts += [f"{why}: {', '.join(items)} — not suggested" for why, items in groups.items()]
    if not parts:
        return []
    return ["the rate limits the diagnosis: " + "; ".join(parts)
            + " (a faster log with a higher --cutoff resolves more)"]
