"""The evidence under a suggestion: how much of its joint's residual a smooth function of the
quantity the effect depends on explains (R², binned), whether it repeats one period on (a
ripple), and the sentence whose numbers are also the suggestion's fields."""

from __future__ import annotations

import numpy as np

from robid_link.ident.model.effects import Block, States
from robid_link.ident.model.robot import Robot

__all__ = ["Signatures", "r2_binned", "signature_r2", "evidence_sentence", "repeats"]


def r2_binned(x: np.ndarray, r: np.ndarray, bins: int = 30) -> float:
    """How much of r a smooth function of x explains (binned means, R²)."""
    if np.ptp(x) <= 0:
        return 0.0
    edges = np.quantile(x, np.linspace(0, 1, bins + 1))
    k = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, bins - 1)
    means = np.bincount(k, weights=r, minlength=bins) / np.maximum(
        np.bincount(k, minlength=bins), 1)
    fitted = means[k]
    return float(1.0 - np.sum((r - fitted) ** 2) / max(np.sum((r - r.mean()) ** 2), 1e-300))


#: what each effect is a function of: the quantity its evidence is stated against
_SIGNATURE = {"spring": "q", "ripple": "q", "armature": "qdd", "friction_drift": "t"}


def signature_r2(robot: Robot, blk: Block, states: States, resid: np.ndarray
                  ) -> dict[str, tuple[str, float]]:
    """R² of the block's primary row's residual against q, the block's velocity (a motor's
    for a motor-side effect), its acceleration and time: key → (label, R²)."""
    j = blk.joint
    assert j is not None
    st = blk.states(robot, states)
    on_motor = blk.effect.sided and st.transmission is not None
    if on_motor:
        assert st.transmission is not None
        v, a, tag = st.qd @ st.transmission[j], st.qdd @ st.transmission[j], f"m{j + 1}"
    else:
        v, a, tag = states.qd[:, j], states.qdd[:, j], f"{j + 1}"
    r = resid[:, j]
    out = {"r2_q": (f"q{j + 1}", r2_binned(states.q[:, j], r)),
           "r2_qd": (f"q̇{tag}", r2_binned(v, r)),
           "r2_qdd": (f"q̈{tag}", r2_binned(a, r))}
    if blk.effect.name == "friction_drift" and states.t is not None:
        # only a drift is weighed against time: at a slow motion's pace, binned time follows
        # everything the motion does
        out["r2_t"] = ("time", r2_binned(states.t, r))
    return out


class Signatures:
    """``signature_r2`` of the residual rows, computed once per joint and side (the first
    candidate there stands for the others)."""

    def __init__(self, robot: Robot, states: States, resid: np.ndarray) -> None:
        self.robot, self.states, self.resid = robot, states, resid
        self._cache: dict[str, dict[str, tuple[str, float]]] = {}

    def of(self, blk: Block) -> dict[str, tuple[str, float]]:
        """key → (label, R²); empty for a global effect."""
        if blk.joint is None:
            return {}
        tag = f"{blk.joint}{blk.side}{blk.effect.name == 'friction_drift'}"
        if tag not in self._cache:
            self._cache[tag] = signature_r2(self.robot, blk, self.states, self.resid)
        return self._cache[tag]


def evidence_sentence(blk: Block, before: float, after: float,
              r2: dict[str, tuple[str, float]], coef: np.ndarray) -> tuple[str, dict[str, float]]:
    """The sentence under a suggestion, stated against the quantity the effect is a function
    of (a friction's velocity, a spring's angle …), so that it cannot contradict it."""
    name = blk.effect.name
    fields = {"rmse_before": round(before, 4), "rmse_after": round(after, 4)}
    drop = (f"cross-validated RMSE of the filtered torque {fields['rmse_before']:.4g} → "
            f"{fields['rmse_after']:.4g} N·m")
    if blk.joint is None:
        if name == "delay":
            secs = float(coef[0]) if coef.size else 0.0
            fields["seconds"] = round(secs, 5)
            return (f"the torque log is shifted by {1e3 * fields['seconds']:.4g} ms against "
                    f"the positions; {drop}", fields)
        return f"{drop}", fields
    fields.update({k: round(v, 3) for k, (_, v) in r2.items()})
    own = "r2_" + _SIGNATURE.get(name, "qd")
    where = f"joint {blk.joint + 1}" if blk.side != "motor" else f"motor {blk.joint + 1}"
    if name == "offset":
        text = f"{where}: a constant torque"
    else:
        others = [k for k in ("r2_q", "r2_qd", "r2_qdd") if k != own]
        text = (f"{where} residual against {r2[own][0]}: R² {fields[own]:.3g} ("
                + ", ".join(f"{r2[k][0]} {fields[k]:.3g}" for k in others) + ")")
        best = max(r2, key=lambda k: r2[k][1])
        if best != own and r2[best][1] > r2[own][1] + 0.05:
            text += (f"; it follows {r2[best][0]} more closely, and the effect still cuts "
                     "the held-out error")
    text += f"; {drop}"
    for key in ("vs", "vp", "period", "tau_s", "alpha"):
        if key in blk.opts:
            fields[key] = round(float(blk.opts[key]), 5)
            text += f"; {key} {fields[key]:.4g}"
    return text, fields


def repeats(q: np.ndarray, r: np.ndarray, period: float) -> float:
    """Correlation of the residual's mean over the angle with itself one period on: near 1
    for cogging or meshing (it repeats), low for a spring (smooth over the travel)."""
    per = 16
    width = period / per
    k = np.floor((q - q.min()) / width).astype(np.int64)
    counts = np.bincount(k)
    means = np.bincount(k, weights=r) / np.maximum(counts, 1)
    ok = (counts[:-per] > 0) & (counts[per:] > 0)
    if ok.sum() < per:
        return 0.0
    a, b = means[:-per][ok], means[per:][ok]
    if a.std() <= 0 or b.std() <= 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])
