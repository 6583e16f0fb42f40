"""Physically consistent identification with the CAD model as prior (issue 15, item 6).

Owns the log-Cholesky parametrization of each link's pseudo-inertia, the prior-regularized
Gauss–Newton fit on the compact Grams, and the choice of the prior's weight λ by cross-validation.

Math (numbered as in the notes of a result):

1. Each link's 4×4 pseudo-inertia J = [[Σ, h], [hᵀ, m]] (Σ = ½ tr(Ī)·1 − Ī about the joint
   frame, h = m·c) is J = U Uᵀ with U = e^α [[e^d₁, s₁₂, s₁₃, t₁], [0, e^d₂, s₂₃, t₂],
   [0, 0, e^d₃, t₃], [0, 0, 0, 1]] (Rucker & Wensing 2022): J ≻ 0 (physically realizable:
   m > 0, triangle inequalities of the principal moments) for every φ = (α, d, s, t).
2. Objective: (1/N)‖τ − Y θ‖² + λ Σ_links [tr(J₀⁻¹J) − log det(J₀⁻¹J) − 4], Lee & Park's
   entropic (log-det Bregman) divergence of pseudo-inertias from the CAD J₀: frame- and
   unit-invariant, and a barrier that keeps each J strictly positive definite. The data term
   is θᵀAθ − 2bᵀθ + c from the training Grams, so no regressor is rebuilt while iterating;
   tr(J₀⁻¹J) is linear in θ and log det J linear in φ (Levenberg–Marquardt on 10 n unknowns).
3. The other effects' parameters (friction, offsets, …) enter linearly without a prior and
   are eliminated (variable projection: Schur complement of the Gram), then recovered.
4. λ by cross-validation on the training data only: leave one motion out when the files hold
   several different motions, else blocked CV over time (5 contiguous folds, one block of
   gap on each side, the same time span held out of every repetition of the motion). λ = ∞
   (the CAD inertials, effects fitted) is a candidate; the largest λ within one standard
   error of the best CV score is chosen (the prior is preferred when the data cannot tell).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robid_link.exceptions import EstimationError
from robid_link.ident.data.logs import Log
from robid_link.ident.data.preprocess import Piece
from robid_link.ident.fit.design import Design
from robid_link.ident.fit.estimate import Grams, accumulate, joint_stats
from robid_link.ident.fit.pseudo import (
    from_log_cholesky,
    lm_solve,
    log_cholesky,
    pseudo_inertia,
    standard_from_pseudo,
)

__all__ = ["ConsistentFit", "fit_consistent", "pseudo_inertia", "standard_from_pseudo",
           "log_cholesky", "from_log_cholesky", "same_motion", "motion_groups", "LAMBDA_GRID"]

#: λ / (mean squared training torque) candidates; ∞ (the CAD inertials) is added
LAMBDA_GRID = tuple(10.0 ** e for e in np.arange(-7.0, 1.01, 0.5))
#: LM stops when a step lowers the objective by less than this × mean squared torque
TOL_REL = 1e-10
#: blocked CV folds within one motion
N_FOLDS = 5
#: relative eigenvalue floor of the (scaled) Grams
_EIG_TOL = 1e-12
#: smallest eigenvalue (relative to the largest) forced on a CAD pseudo-inertia
_CAD_FLOOR = 1e-6


# ----------------------------------------------------------------------- pseudo-inertias

def _realizable(j: np.ndarray) -> np.ndarray:
    """Nudge pseudo-inertias onto the positive definite cone (CAD links may be degenerate)."""
    w, v = np.linalg.eigh(j)
    floor = _CAD_FLOOR * np.maximum(w[:, -1:], 1e-9)
    return (v * np.maximum(w, floor)[:, None, :]) @ np.swapaxes(v, -1, -2)


def _whitened_map(j0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per link: M (10×10) with Mθ = the 10 entries of J₀^{-½} J(θ) J₀^{-½} (off-diagonals ×√2,
    so ‖Mθ − Mθ₀‖ is the Frobenius norm of note 2), and the block-diagonal M of all links."""
    n = j0.shape[0]
    w, v = np.linalg.eigh(j0)
    inv_sqrt = (v / np.sqrt(w)[:, None, :]) @ np.swapaxes(v, -1, -2)
    iu = np.triu_indices(4)
    wt = np.where(iu[0] == iu[1], 1.0, math.sqrt(2.0))
    basis = pseudo_inertia(np.eye(10))  # (10, 4, 4): J of each unit parameter
    blocks = np.einsum("nab,kbc,ncd->nkad", inv_sqrt, basis, inv_sqrt)[:, :, iu[0], iu[1]]
    per_link = np.swapaxes(blocks * wt, -1, -2)  # (n, 10 entries, 10 params)
    full = np.zeros((10 * n, 10 * n))
    for i in range(n):
        full[10 * i: 10 * i + 10, 10 * i: 10 * i + 10] = per_link[i]
    return per_link, full


# ----------------------------------------------------------------------- motions

def same_motion(a: Log, b: Log, tol_rad: float = 0.02) -> bool:
    """Two logs of one trajectory (repetitions are not independent motions)."""
    n = min(len(a), len(b))
    return bool(n > 10 and abs(len(a) - len(b)) <= 0.05 * n
                and np.abs(a.q[:n] - b.q[:n]).max() < tol_rad)


def motion_groups(logs: Sequence[Log]) -> list[list[int]]:
    """Indices of the logs grouped by motion, in order of first appearance."""
    groups: list[list[int]] = []
    for i, lg in enumerate(logs):
        for g in groups:
            if same_motion(logs[g[0]], lg):
                g.append(i)
                break
        else:
            groups.append([i])
    return groups


# ----------------------------------------------------------------------- quadratics

@dataclass
class _Quad:
    """(1/N)‖τ − Xθ‖² = θᵀAθ − 2bᵀθ + c, over N samples."""

    a: np.ndarray
    b: np.ndarray
    c: float
    n: float

    def __add__(self, other: _Quad) -> _Quad:
        tot = self.n + other.n
        return _Quad((self.n * self.a + other.n * other.a) / tot,
                     (self.n * self.b + other.n * other.b) / tot,
                     (self.n * self.c + other.n * other.c) / tot, tot)

    def value(self, theta: np.ndarray) -> float:
        return float(theta @ self.a @ theta - 2.0 * self.b @ theta + self.c)


def _quad(g: np.ndarray) -> _Quad:
    """From augmented Grams summed over joints and the blocks wanted: (p+2, p+2) per joint."""
    p = g.shape[-1] - 2
    tot = g.sum(axis=0)
    n = float(g[:, p + 1, p + 1].max())  # samples (a partial log's: of the joints it holds)
    if n <= 0:
        raise EstimationError("a cross-validation fold has no samples")
    return _Quad(tot[:p, :p] / n, tot[:p, p] / n, float(tot[p, p]) / n, n)


def _pinv_sym(a: np.ndarray) -> np.ndarray:
    if a.size == 0:
        return a
    w, v = np.linalg.eigh(a)
    keep = w > max(w[-1], 1e-300) * _EIG_TOL
    return (v[:, keep] / w[keep]) @ v[:, keep].T


@dataclass
class _Reduced:
    """The data term with the effects' parameters projected out (note 3): πᵀAπ − 2bᵀπ + c."""

    a: np.ndarray
    b: np.ndarray
    back: np.ndarray  # effects = back_b − back π
    back_b: np.ndarray


def _reduce(q: _Quad, n_rigid: int) -> _Reduced:
    r, e = slice(0, n_rigid), slice(n_rigid, q.a.shape[0])
    a_ee_inv = _pinv_sym(q.a[e, e])
    back = a_ee_inv @ q.a[e, r]
    back_b = a_ee_inv @ q.b[e]
    a_red = q.a[r, r] - q.a[r, e] @ back
    return _Reduced(0.5 * (a_red + a_red.T), q.b[r] - q.a[r, e] @ back_b, back, back_b)


@dataclass
class _Prior:
    """The entropic divergence of note 2 per link: tr(J₀⁻¹J) − log det(J₀⁻¹J) − 4 with
    tr(J₀⁻¹J) = wᵀπ (linear) and log det J = 2(4α + d₁ + d₂ + d₃) (linear in φ)."""

    w: np.ndarray  # (10 n,)
    l0_inv: np.ndarray  # (n, 4, 4): tr(J₀⁻¹UUᵀ) = ‖L₀⁻¹U‖²
    logdet0: np.ndarray  # (n,)

    @classmethod
    def of(cls, j0: np.ndarray) -> _Prior:
        j0_inv = np.linalg.inv(j0)
        basis = pseudo_inertia(np.eye(10))
        w = np.einsum("nab,kba->nk", j0_inv, basis).ravel()
        l0_inv = np.linalg.inv(np.linalg.cholesky(j0))
        return cls(w, l0_inv, np.linalg.slogdet(j0)[1])

    def value(self, pi: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Per link divergence at π = π(φ)."""
        tr = (self.w * pi).reshape(-1, 10).sum(axis=1)
        logdet = 2.0 * (4.0 * phi[:, 0] + phi[:, 1:4].sum(axis=1))
        return tr - logdet + self.logdet0 - 4.0


def _solve(red: _Reduced, lam: float, prior: _Prior, phi0: np.ndarray, tol: float,
           max_iter: int = 200) -> tuple[np.ndarray, np.ndarray, int]:
    """Levenberg–Marquardt in φ for one λ on the compact normal equations
    (``pseudo.lm_solve``, compiled).

    F(φ) = πᵀAπ − 2bᵀπ + λ(wᵀπ − log det J): the data term's Gauss–Newton Hessian is DᵀAD
    with D = dπ/dφ block-diagonal (10 × 10 per link), the prior's is that of ‖L₀⁻¹U‖².
    Stops when an accepted step lowers F by less than ``tol`` ((N·m)², absolute).
    Returns φ, π and the number of objective evaluations.
    """
    phi, pi, nfev = lm_solve(red.a, red.b, float(lam), prior.w, prior.l0_inv,
                             np.ascontiguousarray(phi0, dtype=float), float(tol), max_iter)
    return phi, pi, int(nfev)


# ----------------------------------------------------------------------- the fit

@dataclass
class ConsistentFit:
    """The consistent estimate: standard inertial + effect parameters, λ and its CV curve."""

    theta: np.ndarray  # all columns of the design: 10 n standard, then the effects'
    names: list[str]
    theta_cad: np.ndarray  # the prior's 10 n standard parameters
    lam: float  # absolute (N·m)² per unit divergence; inf = the CAD inertials
    lam_rel: float  # λ / mean squared training torque
    cv_scheme: str
    cv_curve: list[dict[str, float | None]]
    min_eig: np.ndarray  # smallest eigenvalue of each link's pseudo-inertia (> 0)
    n_evaluations: int
    design: Design = field(repr=False)
    rss: np.ndarray = field(repr=False)  # per joint, training
    mean_res: np.ndarray = field(repr=False)
    cov: np.ndarray = field(repr=False)
    validation_ols: dict[str, Any] | None = None  # set by identify: OLS on the same inputs

    @property
    def standard(self) -> np.ndarray:
        return self.theta[: self.theta_cad.size]

    def divergence(self) -> np.ndarray:
        """Per link entropic divergence (note 2) of the estimate from the CAD prior."""
        j0 = _realizable(pseudo_inertia(self.theta_cad.reshape(-1, 10)))
        j = pseudo_inertia(self.standard.reshape(-1, 10))
        m = np.linalg.solve(j0, j)
        return np.trace(m, axis1=-2, axis2=-1) - np.linalg.slogdet(m)[1] - 4.0

    def as_dict(self) -> dict[str, Any]:
        fin = math.isfinite(self.lam)
        return {
            "lambda": self.lam if fin else None,
            "lambda_relative": self.lam_rel if fin else None,
            "lambda_is_cad": not fin,
            "cv_scheme": self.cv_scheme,
            "cv_curve": self.cv_curve,
            "min_eig_pseudo_inertia": [float(v) for v in self.min_eig],
            "physically_consistent": bool(np.all(self.min_eig > 0)),
            "divergence_from_cad": [float(v) for v in self.divergence()],
            "standard": {nm: float(v) for nm, v in zip(self.names, self.theta, strict=True)},
            "standard_cad": {nm: float(v) for nm, v in
                             zip(self.names, self.theta_cad, strict=False)},
            "validation_ols": self.validation_ols,
        }


def pieces_by_file(train: Sequence[Piece]) -> tuple[list[Log], list[list[Piece]]]:
    """The training pieces grouped by their log, in order of first appearance."""
    files: list[Log] = []
    per_file: list[list[Piece]] = []
    for pc in train:
        for k, lg in enumerate(files):
            if lg is pc.prep.log:
                per_file[k].append(pc)
                break
        else:
            files.append(pc.prep.log)
            per_file.append([pc])
    return files, per_file


def fit_consistent(design: Design, train: Sequence[Piece], names: Sequence[str], *,
                   nominal: np.ndarray | None, interval: int, block_len: int,
                   lam: float | None = None,
                   grams: Sequence[Grams] | None = None) -> ConsistentFit:
    """Fit standard inertial parameters (log-Cholesky) + effects with the CAD prior.

    ``design`` must hold all columns (standard parameters first, effects after). With ``lam``
    None, λ is chosen by cross-validation on ``train`` (note 4); the validation data is never
    seen here. ``grams``: the design's Grams per file of ``pieces_by_file(train)``, when the
    caller has them already.
    """
    robot = design.robot
    n_rigid = 10 * robot.n
    if nominal is None:
        raise EstimationError(f"{robot.source}: --method consistent needs the robot's "
                              "inertials as prior (URDF <inertial> or MDH 'inertial:' entries); "
                              "this robot file has none")
    if design.p < n_rigid or not np.array_equal(design.cols[:n_rigid], np.arange(n_rigid)) \
            or design.blocks[0].effect.name != "rigid_body":
        raise EstimationError("--method consistent needs the model's rigid_body effect first "
                              "and all its standard columns in the design")
    files, per_file = pieces_by_file(train)
    if grams is None:
        grams = [accumulate(design, pcs, interval, block_len) for pcs in per_file]
    theta_cad = np.asarray(nominal, dtype=float)
    j0 = _realizable(pseudo_inertia(theta_cad.reshape(-1, 10)))
    _, m_full = _whitened_map(j0)
    prior = _Prior.of(j0)
    phi_cad = log_cholesky(j0)
    total = _total(grams)
    scale = max(total.c, 1e-300)
    groups = motion_groups(files)
    folds, scheme = _folds(grams, groups)
    nfev = 0
    if lam is None:
        curve, nfev = _cv_curve(folds, n_rigid, prior, phi_cad, scale, theta_cad)
        lam_rel = _one_se_choice(curve)
    else:
        lam_rel = lam / scale
        curve = []
    lam_abs = lam_rel * scale
    red = _reduce(total, n_rigid)
    if math.isfinite(lam_abs):
        phi, pi, k = _solve(red, lam_abs, prior, phi_cad, TOL_REL * scale)
        nfev += k
    else:
        phi, pi = phi_cad, standard_from_pseudo(j0).ravel()
    theta = np.concatenate((pi, red.back_b - red.back @ pi))
    min_eig = np.linalg.eigvalsh(pseudo_inertia(from_log_cholesky(phi)[0]))[:, 0]
    g_tot = np.sum([gr.total() for gr in grams], axis=0)
    rss, mean_res = joint_stats(g_tot, theta)
    cov = _covariance(total, g_tot, theta, rss, n_rigid, lam_abs, m_full)
    return ConsistentFit(theta, [names[int(c)] for c in design.cols], theta_cad, lam_abs,
                         lam_rel, scheme, curve, min_eig, nfev, design, rss, mean_res, cov)


def _total(grams: Sequence[Grams]) -> _Quad:
    out = _quad(grams[0].total())
    for g in grams[1:]:
        out = out + _quad(g.total())
    return out


def _folds(grams: Sequence[Grams], groups: list[list[int]]
           ) -> tuple[list[tuple[_Quad, _Quad]], str]:
    """(train, held-out) quadratics per fold (note 4)."""
    if len(groups) > 1:
        folds = []
        for g in groups:
            held = _total([grams[i] for i in g])
            rest = _total([grams[i] for i in range(len(grams)) if i not in g])
            folds.append((rest, held))
        return folds, f"leave one motion out ({len(groups)} motions)"
    parts: list[list[tuple[_Quad, _Quad]]] = [[] for _ in range(N_FOLDS)]
    for gr in grams:
        nb = gr.g.shape[1]
        fold = (np.arange(nb) * N_FOLDS) // nb
        test = fold[None, :] == np.arange(N_FOLDS)[:, None]  # (folds, blocks)
        near = np.stack([np.convolve(t.astype(float), np.ones(3), mode="same") > 0
                         for t in test])
        # one pass over the blocks: the sums of the runs of blocks whose role is the same
        # in every fold, then each fold's held-out and training sums from those few runs
        roles = np.concatenate((test, near))
        cuts = np.concatenate(([0], np.flatnonzero(np.any(roles[:, 1:] != roles[:, :-1],
                                                          axis=0)) + 1))
        runs = np.add.reduceat(gr.g, cuts, axis=1)
        for k in range(N_FOLDS):
            parts[k].append((_quad(runs[:, ~near[k, cuts]].sum(axis=1)),
                             _quad(runs[:, test[k, cuts]].sum(axis=1))))
    folds = []
    for files in parts:  # one fold's (train, held-out) of each file, summed
        tr, te = files[0]
        for a, b in files[1:]:
            tr, te = tr + a, te + b
        folds.append((tr, te))
    what = "one motion" if len(grams) == 1 else f"one motion repeated in {len(grams)} files"
    return folds, (f"blocked CV over time, {N_FOLDS} contiguous folds with a one-block gap "
                   f"({what}; the same time span held out of every file)")


def _cv_curve(folds: list[tuple[_Quad, _Quad]], n_rigid: int, prior: _Prior,
              phi_cad: np.ndarray, scale: float, theta_cad: np.ndarray
              ) -> tuple[list[dict[str, float | None]], int]:
    """Held-out mean squared torque error (N·m)² per λ, largest λ first (warm starts)."""
    grid = sorted(LAMBDA_GRID, reverse=True)
    scores = np.zeros((len(grid) + 1, len(folds)))
    nfev = 0
    for f, (tr, te) in enumerate(folds):
        red = _reduce(tr, n_rigid)
        scores[0, f] = te.value(np.concatenate((theta_cad, red.back_b - red.back @ theta_cad)))
        phi = phi_cad
        for gi, rel in enumerate(grid, 1):
            phi, pi, k = _solve(red, rel * scale, prior, phi, TOL_REL * scale)
            nfev += k
            scores[gi, f] = te.value(np.concatenate((pi, red.back_b - red.back @ pi)))
    weights = np.array([te.n for _, te in folds])
    mean = scores @ weights / weights.sum()
    se = scores.std(axis=1, ddof=1) / math.sqrt(len(folds)) if len(folds) > 1 else 0 * mean
    lams = [math.inf, *grid]
    return [{"lambda_relative": None if not math.isfinite(lv) else float(lv),
             "cv_mse": float(m), "cv_se": float(s)}
            for lv, m, s in zip(lams, mean, se, strict=True)], nfev


def _one_se_choice(curve: list[dict[str, float | None]]) -> float:
    """The largest λ whose CV error is within one standard error of the best (note 4)."""
    mse = np.array([c["cv_mse"] for c in curve], dtype=float)
    best = int(np.argmin(mse))
    bound = mse[best] + float(curve[best]["cv_se"] or 0.0)
    for c in curve:  # largest λ first
        if float(c["cv_mse"] or 0.0) <= bound:
            lv = c["lambda_relative"]
            return math.inf if lv is None else float(lv)
    return float(curve[best]["lambda_relative"] or math.inf)


def _covariance(total: _Quad, g_tot: np.ndarray, theta: np.ndarray, rss: np.ndarray,
                n_rigid: int, lam: float, m_full: np.ndarray) -> np.ndarray:
    """Sandwich covariance of the regularized estimate, the constraint ignored (a guide only:
    residual correlation from filtering is not accounted for)."""
    p = theta.size
    h = total.a.copy()
    if math.isfinite(lam):
        h[:n_rigid, :n_rigid] += lam * m_full.T @ m_full
    else:
        h[:n_rigid, :n_rigid] += 1e12 * np.eye(n_rigid) * max(np.trace(h) / p, 1e-300)
    h_inv = _pinv_sym(0.5 * (h + h.T))
    n = total.n
    var = rss / max(n, 1.0)
    meat = np.einsum("j,jik->ik", var, g_tot[:, :p, :p]) / (n * n)
    return h_inv @ meat @ h_inv
