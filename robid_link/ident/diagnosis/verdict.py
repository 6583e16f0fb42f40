"""What a diagnosis returns and what decides it: the suggestion and diagnosis records (summary,
JSON), the thresholds a candidate must pass, the doubts about a model with nothing missing,
and the ranking of the suggestions (physics first, then fewer parameters)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.effects import effect_label

__all__ = ["Suggestion", "Diagnosis", "Verdicts", "GAIN_MIN", "P_MAX", "TRANSFER_MIN",
           "EQUIVALENT", "judge", "rank", "one_by_one", "result_doubts", "floor_doubts",
           "not_transferring_note", "not_repeating_note", "unphysical_note", "physics_order",
           "prefer_simpler"]

#: a suggestion must cut its joint's held-out RMSE by at least this fraction …
GAIN_MIN = 0.05
#: … and be significant at this level (Wald test with the long-run-variance covariance)
P_MAX = 1e-3
#: on the validation logs a suggestion must cut its rows' RMSE by this fraction, and not raise
#: the other joints' (it shares the rigid-body parameters), else it does not transfer
TRANSFER_MIN = 0.01
#: extrapolation notes (validation outside the training ranges) that make a verdict doubtful
EXTRAPOLATION_MAX = 3
#: spring and ripple within this fraction of each other: physics decides (does it repeat?)
NEAR_EQUAL = 0.05
#: correlation of the residual with itself one period on, above which it repeats (ripple);
#: a ripple whose residual does not repeat is no cogging or meshing, whatever it cuts
REPEAT_MIN = 0.5
#: two explanations of one joint leave the same held-out error within this fraction: the log
#: cannot tell them apart
EQUIVALENT = 0.01
#: a Stribeck curve's breakaway (static minus Coulomb friction) more than this many σ below
#: zero is friction rising with speed: not a Stribeck curve, whatever it cuts
BREAKAWAY_SIGMAS = 2.0
#: suggestions spelled out in the terminal summary (all of them go to the JSON)
SUMMARY_MAX = 5


@dataclass
class Suggestion:
    effect: str
    joint: int | None  # from 1; None for a global effect
    rmse: list[float]  # held-out (CV) RMSE per joint with the effect added
    gain: float
    p_value: float
    evidence: str
    fields: dict[str, float] = field(default_factory=dict)
    hypers: dict[str, float] = field(default_factory=dict)
    side: str | None = None  # "joint" / "motor" when the effect names its side
    #: relative cut of the validation logs' RMSE on the effect's rows (None: no such logs)
    transfer: float | None = None
    #: a spring whose law a counterbalance fits: the model file's ``known_torque`` entry
    known_torque: dict[str, Any] | None = None
    #: effects that explain the same as this one on this log (``one_by_one``), by label
    alternatives: list[str] = field(default_factory=list)

    def label(self) -> str:
        return effect_label(self.effect, self.joint, self.side)

    def as_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "joint": self.joint, "side": self.side,
                "label": self.label(), "rmse": self.rmse, "gain": self.gain,
                "transfer_gain": self.transfer, "p_value": self.p_value,
                "evidence": self.evidence, **self.fields, "hyper_parameters": self.hypers,
                **({"known_torque": self.known_torque} if self.known_torque else {}),
                **({"alternatives": self.alternatives} if self.alternatives else {})}


@dataclass
class Diagnosis:
    result: IdentResult
    effects: list[str]
    rmse_cv: list[float] | None  # None: no candidate needed scoring (no union pass)
    suggestions: list[Suggestion]
    rejected: list[Suggestion]
    absorbed: list[dict[str, Any]]
    unexplained: list[dict[str, Any]]
    notes: list[str]
    residuals: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    #: suggestions that won the cross-validation but not on the validation logs
    not_transferring: list[Suggestion] = field(default_factory=list)
    #: why the model cannot be called adequate though nothing is missing
    doubts: list[str] = field(default_factory=list)
    #: suggestions that cut the error but that the log cannot separate (limits.py)
    limited: list[Suggestion] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        if self.suggestions:
            return "missing_effect"
        return "doubtful" if self.doubts else "adequate"

    def to_dict(self) -> dict[str, Any]:
        return {"effects": self.effects, "joints": self.result.joints,
                "rmse": [float(x) for x in self.result.rmse], "rmse_cv": self.rmse_cv,
                "relative_error": self.result.to_dict()["relative_error"],
                "verdict": self.verdict,
                "suggestions": [s.as_dict() for s in self.suggestions],
                "not_useful": [s.as_dict() for s in self.rejected],
                "not_transferring": [s.as_dict() for s in self.not_transferring],
                "limited_by_the_log": [s.as_dict() for s in self.limited],
                "doubts": self.doubts,
                "absorbed": self.absorbed, "unexplained": self.unexplained,
                "notes": self.notes}

    def summary(self) -> str:
        joints = self.result.joints
        lines = [f"robid diagnose — {self.result.robot}: model [{', '.join(self.effects)}]",
                 "  held-out RMSE per joint [N·m]: " + ", ".join(
                     f"{j['joint']}: {r:.3g}" for j, r in zip(joints, self.result.rmse,
                                                              strict=True)),
                 f"  verdict: {self.verdict}"]
        if self.suggestions:
            lines.append("  suggestions, best first:")
            for k, s in enumerate(self.suggestions[:SUMMARY_MAX], 1):
                lines.append(f"   {k}. {s.label():<22} gain {100 * s.gain:5.1f} %   {s.evidence}")
            if len(self.suggestions) > SUMMARY_MAX:
                rest = self.suggestions[SUMMARY_MAX:]
                lines.append(f"   … and {len(rest)} more, weaker ("
                             + ", ".join(s.label() for s in rest[:8])
                             + (", …" if len(rest) > 8 else "") + "; all in the JSON)")
        for s in self.not_transferring[:SUMMARY_MAX]:
            lines.append(f"  does not transfer: {s.label()} (cross-validated gain "
                         f"{100 * s.gain:.1f} %, on the validation logs "
                         f"{100 * (s.transfer or 0.0):+.1f} %)")
        if self.limited:
            lines.append("  the log cannot separate: " + ", ".join(
                f"{s.label()} (gain {100 * s.gain:.1f} %)" for s in self.limited[:SUMMARY_MAX])
                + " — not suggested (see the notes)")
        for d in self.doubts:
            lines.append(f"  doubt: {d}")
        for u in self.unexplained:
            lines.append(f"  unexplained: {u['text']}")
        if self.absorbed:
            lines.append("  absorbed (no new information): " + ", ".join(
                f"{a['effect']} by {', '.join(a['by'][:3])}" for a in self.absorbed[:6]))
        lines += [f"  [{i}] {n}" for i, n in enumerate(self.notes, 1)]
        return "\n".join(lines)


@dataclass(frozen=True)
class Verdicts:
    """The scored candidates by what became of them."""

    suggested: list[Suggestion]  # pass the gain and the test (and transfer, if tested)
    rejected: list[Suggestion]  # too small a gain, or not significant
    not_transferring: list[Suggestion]  # pass, but not on the validation logs


def judge(scored: list[Suggestion]) -> Verdicts:
    """Suggested when the gain is at least GAIN_MIN at p ≤ P_MAX, for a ripple the residual
    repeats one period on and for a Stribeck curve the breakaway is not negative — unless, on
    validation logs, it raises the error or cuts its own rows' by under TRANSFER_MIN; in
    candidate order."""
    good, bad, lost = [], [], []
    for sug in scored:
        if sug.gain >= GAIN_MIN and sug.p_value <= P_MAX and not _not_repeating(sug) \
                and not _unphysical(sug):
            if sug.transfer is not None and (sug.transfer <= 0.0 or
                                             sug.fields["transfer_own"] < TRANSFER_MIN):
                lost.append(sug)
            else:
                good.append(sug)
        else:
            bad.append(sug)
    return Verdicts(good, bad, lost)


def rank(v: Verdicts) -> Verdicts:
    """Suggestions by what transfers to the validation logs when there are some, else by
    the cross-validated gain; then physics, then fewer parameters among equivalents. The
    others by gain."""
    good = sorted(v.suggested, key=lambda s: -(s.transfer if s.transfer is not None
                                               else s.gain))
    return Verdicts(prefer_simpler(physics_order(good)),
                    sorted(v.rejected, key=lambda s: -s.gain),
                    sorted(v.not_transferring, key=lambda s: -s.gain))


def _not_repeating(sug: Suggestion) -> bool:
    return sug.effect == "ripple" and sug.fields.get("repeat", 0.0) < REPEAT_MIN


def not_repeating_note(rejected: list[Suggestion]) -> list[str]:
    """The ripples that cut the error but whose residual does not repeat along the angle."""
    odd = [s for s in rejected if _not_repeating(s) and s.gain >= GAIN_MIN and
           s.p_value <= P_MAX]
    if not odd:
        return []
    return [", ".join(f"{s.label()} (gain {100 * s.gain:.3g} %, correlation one period on "
                      f"{s.fields.get('repeat', 0.0):.2g})" for s in odd[:6])
            + f" cut the error, but the residual does not repeat along the angle one period on "
            f"(correlation under {REPEAT_MIN:g}): not cogging or meshing, not suggested"]


def _unphysical(sug: Suggestion) -> bool:
    """A Stribeck curve whose friction rises from standstill (breakaway below zero beyond
    BREAKAWAY_SIGMAS σ). The sign rule is for Stribeck only: presliding's fp below zero beside
    Coulomb's step is friction falling with speed, and friction_power's velocity term beside
    the model's own viscous friction may bend either way."""
    if sug.effect != "stribeck" or "breakaway" not in sug.fields:
        return False
    return sug.fields["breakaway"] < -BREAKAWAY_SIGMAS * sug.fields["breakaway_sigma"]


def unphysical_note(rejected: list[Suggestion]) -> list[str]:
    """The Stribeck curves that cut the error with a negative breakaway, one line each."""
    return [f"{s.label()} cuts the error (gain {100 * s.gain:.3g} %) but its fitted breakaway "
            f"fst_{'' if s.side is None else s.side[0]}{s.joint} = "
            f"{s.fields['breakaway']:.3g} ± {s.fields['breakaway_sigma']:.2g} N·m is negative: "
            "the friction rises with speed from standstill, not a Stribeck curve (a "
            "velocity-dependent law such as friction_power describes it): not suggested"
            for s in rejected if _unphysical(s) and s.gain >= GAIN_MIN
            and s.p_value <= P_MAX][:6]


Given = Callable[["Suggestion", list["Suggestion"]], tuple[float, float]]


def one_by_one(v: Verdicts, given: Given, apart: Given, nuisance: str = ""
               ) -> tuple[Verdicts, list[str]]:
    """Each suggestion judged with the better ones before it in the model (and ``nuisance``,
    named so, when the callables add one: the log's own sample-and-hold): ``given(s,
    better)`` is its gain and p-value then, ``apart(s, better)`` the same with the rows near the
    velocity reversals left out (``scoring.without_turns``). It stays when both pass GAIN_MIN
    at P_MAX. One that fails ``given`` and leaves the error a better one on its joint leaves
    (within EQUIVALENT) is named as that one's alternative — the log cannot tell them apart;
    the other failures explained only what the better ones leave, or what the model misses at
    the turns. Returns the verdicts and a note per failure."""
    kept: list[Suggestion] = []
    notes: list[str] = []
    gone: list[Suggestion] = []
    for sug in v.suggested:
        why = _after_the_better(sug, kept, given, nuisance) if kept or nuisance else None
        if why == "":  # named as a better one's alternative
            continue
        why = why or _away_from_turns(sug, kept, apart)
        if why:
            gone.append(sug)
            notes.append(why)
        else:
            kept.append(sug)
    rejected = sorted([*v.rejected, *gone], key=lambda s: -s.gain)
    return Verdicts(kept, rejected, v.not_transferring), notes[:6]


def _after_the_better(sug: Suggestion, kept: list[Suggestion], given: Given, nuisance: str
                      ) -> str | None:
    """None when ``sug`` still helps with ``kept`` (and the nuisance) in the model; "" when
    it is a kept one's alternative (named there); else why it is not suggested."""
    gain, p_value = given(sug, kept)
    sug.fields["gain_given"] = round(gain, 4)
    if gain >= GAIN_MIN and p_value <= P_MAX:
        return None
    twin = next((k for k in kept if k.joint == sug.joint and _equivalent(k, sug)), None)
    if twin is not None:
        twin.alternatives.append(sug.label())
        twin.evidence += (f"; {sug.label()} explains it as well (the same held-out error "
                          "within a percent): the log cannot tell them apart")
        return ""
    names = [k.label() for k in kept] + ([nuisance] if nuisance else [])
    better = ", ".join(names)
    return (f"{sug.label()} (gain {100 * sug.gain:.3g} % alone, {100 * gain:.2g} % with "
            f"{better} in the model) explains only what "
            f"{'those leave' if len(names) > 1 else 'that leaves'}: not suggested")


def _away_from_turns(sug: Suggestion, kept: list[Suggestion], apart: Given) -> str | None:
    """None when ``sug`` keeps its gain with the rows near the turns left out, else why not."""
    gain, p_value = apart(sug, kept)
    sug.fields["gain_apart"] = round(gain, 4)
    if gain >= GAIN_MIN and p_value <= P_MAX:
        return None
    return (f"{sug.label()} (gain {100 * sug.gain:.3g} %) keeps {100 * gain:.2g} % when the rows "
            "near the velocity reversals are left out: what the model misses at a turn finer "
            "than the filter resolves (a stick, a closed loop's Coulomb switch) recurs where the "
            "motion turns again and biases the parameters the joints share, and that is what "
            "it explained — not suggested")


def _equivalent(a: Suggestion, b: Suggestion) -> bool:
    ra, rb = a.fields["rmse_after"], b.fields["rmse_after"]
    return abs(ra - rb) <= EQUIVALENT * max(ra, rb, 1e-12)


def not_transferring_note(lost: list[Suggestion]) -> list[str]:
    if not lost:
        return []
    return [f"{', '.join(s.label() for s in lost[:6])} won the cross-validation but "
            "did not cut the error on the validation logs: not suggested"]


def result_doubts(result: IdentResult) -> list[str]:
    """Why a model with nothing missing still cannot be called adequate: piled-up
    extrapolation, and what makes the fit unfit (physically impossible, worse than CAD)."""
    out = []
    extrap = [n for n in result.notes if "the model extrapolates" in n]
    if len(extrap) >= EXTRAPOLATION_MAX:
        out.append(f"{len(extrap)} extrapolation warnings: the validation motion leaves the "
                   "training ranges, so its error says little about the model")
    return out + result.doubts


def floor_doubts(result: IdentResult, turns: Mapping[int, Any] | None = None) -> list[str]:
    """A joint whose held-out residual is not measurement noise — above the noise estimate
    (AT_FLOOR×), or near it in size but not white — is not modelled adequately, whether or
    not a catalog effect is suggested for it. ``turns``: joint (from 0) → where its residual
    sits (``residuals.Turns``), said in its doubt."""
    try:
        at, val = result.at_noise_floor, result.validation
    except (AttributeError, ValueError):  # no held-out rows
        return []
    floor, white = result.noise_floor, result.whiteness
    if at is None or val is None or floor is None or white is None:
        return []
    out = []
    for j, ok in enumerate(at):
        if ok:
            continue
        ratio = float(val.rmse[j] / max(floor[j], 1e-300))
        size = (f"held-out error {val.rmse[j]:.3g} N·m is {ratio:.2g}× the noise estimate "
                f"{floor[j]:.3g} N·m")
        why = white.sentence(j) if not white.white[j] else "its residual is white"
        where = f"; {turns[j].sentence()}" if turns and j in turns else ""
        out.append(f"joint {result.joints[j]['joint']}: {size} and {why}: the model leaves "
                   f"more than measurement noise{where}")
    return out


def physics_order(good: list[Suggestion]) -> list[Suggestion]:
    """A spring and a ripple on one joint within NEAR_EQUAL of each other: what physics says
    of each decides — cogging repeats along the angle, a spring does not."""
    out = list(good)
    for i, a in enumerate(out):
        for k in range(i + 1, len(out)):
            b = out[k]
            if a.joint != b.joint or {a.effect, b.effect} != {"spring", "ripple"}:
                continue
            near = abs(a.fields["rmse_after"] - b.fields["rmse_after"]) <= NEAR_EQUAL * max(
                a.fields["rmse_after"], b.fields["rmse_after"], 1e-12)
            ripple = a if a.effect == "ripple" else b
            repeats = ripple.fields.get("repeat", 0.0) >= REPEAT_MIN
            if near and (a is ripple) != repeats:
                out[i], out[k] = b, a
            break
    return out


def prefer_simpler(good: list[Suggestion]) -> list[Suggestion]:
    """Among near-equal explanations on one joint, the one with fewer parameters first."""
    order = {"offset": 1, "viscous": 1, "friction": 1, "coulomb": 1, "armature": 1,
             "load_friction": 1, "stribeck": 1, "presliding": 1, "coulomb_asymmetric": 2,
             "ripple": 2, "friction_drift": 2, "friction_power": 3, "spring": 9, "delay": 1}
    out = list(good)
    swapped = True
    while swapped:  # bubble until stable: equivalents may come in any order
        swapped = False
        for i in range(len(out) - 1):
            a, b = out[i], out[i + 1]
            close = abs(a.fields["rmse_after"] - b.fields["rmse_after"]) <= 0.01 * max(
                a.fields["rmse_after"], 1e-12)  # equivalent: the same error left, within 1 %
            if {a.effect, b.effect} == {"spring", "ripple"}:
                continue  # physics decides those (physics_order)
            if a.joint == b.joint and close and order.get(b.effect, 9) < order.get(a.effect, 9):
                out[i], out[i + 1] = b, a
                swapped = True
    return out
