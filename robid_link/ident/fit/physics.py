"""Physical sense of a fit before anything is stored or sent: a base parameter that sums
quantities no body has negative (masses, the diagonal of an inertia, rotor inertia, friction)
estimated significantly below zero, and held-out errors above the a-priori (CAD) model's. Each
doubt names what is wrong and the remedy: the physically consistent estimator with the CAD
prior (``--method consistent``, ``fit/consistent.py``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from robid_link.ident.fit.design import base_set_for

if TYPE_CHECKING:
    from robid_link.ident.fit.results import IdentResult

__all__ = ["fit_doubts", "impossible_parameters", "worse_than_cad", "NEGATIVE_SIGMAS",
           "CAD_MARGIN", "REMEDY"]

#: a sign-definite base parameter this many standard deviations below zero is impossible
NEGATIVE_SIGMAS = 2.0
#: a joint validates worse than CAD when its held-out RMSE exceeds CAD's by this factor
CAD_MARGIN = 1.1
#: standard parameters whose value no body can have negative (by name prefix)
_NON_NEGATIVE = {"m", "xx", "yy", "zz", "ia", "fv", "fc"}
REMEDY = ("refit with --method consistent (campaign method: consistent): every link a body "
          "that can exist, pulled towards CAD where the data say little")


def _prefix(name: str) -> str:
    return name.rpartition("_")[0]


def impossible_parameters(result: IdentResult) -> list[tuple[str, float, float]]:
    """(name, value, σ) of base parameters that are positive combinations of non-negative
    standard parameters (zz_1 + yy_2 + 0.16·m_3 …: no body makes them negative) estimated more
    than NEGATIVE_SIGMAS below zero. A consistent fit's standard parameters are physical by
    construction: none."""
    pb = result.problem
    if pb is None or result.method == "consistent":
        return []
    base, _ = base_set_for(pb.robot, pb.blocks, pb.transmission)
    out = []
    for k, p in enumerate(result.parameters):
        row = base.combination[k]
        used = np.flatnonzero(row)
        definite = used.size and all(_prefix(base.names[i]) in _NON_NEGATIVE and row[i] > 0
                                     for i in used)
        if definite and p.value < -NEGATIVE_SIGMAS * p.std:
            out.append((p.name, p.value, p.std))
    return out


def worse_than_cad(result: IdentResult) -> tuple[list[int], bool]:
    """(joints from 0 whose held-out RMSE exceeds CAD_MARGIN × the CAD model's, whether the
    held-out relative error exceeds CAD's); nothing without a CAD model or held-out rows."""
    try:
        val, nom = result.validation, result.nominal
    except (AttributeError, ValueError):
        return [], False
    if val is None or nom is None:
        return [], False
    joints = [j for j in range(len(val.rmse)) if val.rmse[j] > CAD_MARGIN * nom.rmse[j]]
    overall = (val.relative_error is not None and nom.relative_error is not None
               and val.relative_error > nom.relative_error)
    return joints, overall


def fit_doubts(result: IdentResult) -> list[str]:
    """What makes the fit unfit to hand a controller, each with the remedy."""
    out = []
    bad = impossible_parameters(result)
    if bad:
        out.append("physically impossible: " + ", ".join(
            f"{name} = {value:.4g} ± {std:.2g}" for name, value, std in bad)
            + " (sums of masses and moments of inertia no body has negative); " + REMEDY)
    joints, overall = worse_than_cad(result)
    if joints or overall:
        val, nom = result.validation, result.nominal
        assert val is not None and nom is not None
        names = [result.joints[j]["joint"] for j in joints]
        parts = []
        if overall:
            parts.append(f"held-out relative error {100 * (val.relative_error or 0):.3g} % "
                         f"is above the a-priori (CAD) model's "
                         f"{100 * (nom.relative_error or 0):.3g} %")
        if joints:
            parts.append(f"joint(s) {', '.join(map(str, names))} validate worse than the CAD "
                         "model (RMSE " + ", ".join(f"{val.rmse[j]:.3g} vs {nom.rmse[j]:.3g}"
                                                    for j in joints) + " N·m)")
        remedy = (REMEDY if result.method != "consistent" else
                  "the data do not support moving away from CAD: excite those joints more, "
                  "or look for what the model lacks (robid diagnose)")
        out.append("; ".join(parts) + "; " + remedy)
    return out
