"""Choosing a candidate effect's free hyper-parameter (Stribeck velocity, ripple period,
friction exponent, drift time constant …) and screening candidates, on the current model's
residual at a few thousand rows spread over the log — no column is filtered here."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from robid_link.ident.model.effects import REGISTRY, Block, States
from robid_link.ident.model.robot import Robot

#: friction_drift's time constants from here on mean a linear drift (see model/catalog.py)
LINEAR_DRIFT = 1e5

__all__ = ["ProfileRows", "profile_effect", "refine_effect", "screen", "screens", "basis",
           "bounds", "Beyond", "ModelSpan"]


def basis(x: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the column space of ``x`` (SVD, relative floor 1e-10)."""
    u, sv, _ = np.linalg.svd(x, full_matrices=False)
    return u[:, sv > sv[0] * 1e-10] if sv.size and sv[0] > 0 else u[:, :0]


@dataclass
class ProfileRows:
    """The rows one diagnosis profiles and screens on, with the bases it projects off (each
    computed once, on first use)."""

    robot: Robot
    states: States
    resid: np.ndarray  # raw torque minus the current model (profiling: no column filtered)
    resid_filtered: np.ndarray  # the parallel-filtered residual (screen, ripple spectrum)
    model_cols: np.ndarray  # the model's dense regressor on these rows (N, n, p)
    #: the grids' shares by candidate and hyper-parameters (Stribeck's two rounds repeat some)
    tried: dict[tuple[str, tuple[tuple[str, float], ...]], float] = field(
        default_factory=dict, repr=False)
    _helpers: dict[tuple[int, ...], np.ndarray] = field(default_factory=dict, repr=False)
    _beyonds: dict[tuple[int, ...], Beyond] = field(default_factory=dict, repr=False)
    _beyond_model: Beyond | None = field(default=None, repr=False)
    _model_span: ModelSpan | None = field(default=None, repr=False)

    def rows_of(self, blk: Block) -> list[int]:
        """The joints whose torque ``blk`` loads (a coupled motor's friction: several)."""
        return blk.rows(self.robot, self.states.transmission)

    def helper_basis(self, joints: Sequence[int]) -> np.ndarray:
        """Basis of each joint's own viscous, Coulomb and offset columns and its model row,
        on the joints' rows stacked sample after sample (N·len(joints) rows)."""
        key = tuple(joints)
        if key not in self._helpers:
            per = []
            for j in key:
                parts = [REGISTRY[name].columns(self.robot, self.states, j, {})[:, j, :]
                         for name in ("viscous", "coulomb", "offset")]
                own = self.model_cols[:, j, :]
                parts.append(own[:, np.abs(own).max(axis=0) > 0])
                per.append(basis(np.concatenate(parts, axis=1)))
            if len(per) == 1:  # the layout below, without the copy
                self._helpers[key] = np.ascontiguousarray(per[0])
                return self._helpers[key]
            out = np.zeros((per[0].shape[0], len(key), sum(b.shape[1] for b in per)))
            at = 0
            for r, b in enumerate(per):
                out[:, r, at: at + b.shape[1]] = b
                at += b.shape[1]
            self._helpers[key] = out.reshape(-1, out.shape[2])
        return self._helpers[key]

    def beyond(self, blk: Block) -> Beyond:
        """The raw residual of the joints ``blk`` loads, beyond their helpers
        (``helper_basis``); a global effect's: every joint's residual together, no helpers."""
        if blk.joint is None:
            if () not in self._beyonds:
                self._beyonds[()] = Beyond(np.zeros((self.resid.size, 0)),
                                           self.resid.reshape(-1))
            return self._beyonds[()]
        rows = self.rows_of(blk)
        key = tuple(rows)
        if key not in self._beyonds:
            self._beyonds[key] = Beyond(self.helper_basis(rows), self.resid[:, rows].reshape(-1))
        return self._beyonds[key]

    def stacked(self, blk: Block, cols: np.ndarray) -> np.ndarray:
        """A block's (N, n, k) columns on its rows, stacked like ``beyond``'s residual."""
        return cols[:, self.rows_of(blk), :].reshape(-1, cols.shape[2])

    def own_columns(self, blk: Block) -> np.ndarray:
        """``stacked`` of the block's columns, built on its rows only; a global effect's on
        every joint's rows, stacked as ``beyond``'s residual."""
        if blk.joint is None:
            cols = blk.columns(self.robot, self.states)
            return cols.reshape(-1, cols.shape[2])
        on, cols = blk.row_columns(self.robot, self.states)
        if on != self.rows_of(blk):  # loads other rows than it names: the dense columns
            return self.stacked(blk, blk.columns(self.robot, self.states))
        return cols.reshape(-1, cols.shape[2])

    @property
    def beyond_model(self) -> Beyond:
        """The filtered residual (joints stacked) projected off the model's column space."""
        if self._beyond_model is None:
            model = basis(self.model_cols.reshape(-1, self.model_cols.shape[2]))
            self._beyond_model = Beyond(model, self.resid_filtered.reshape(-1))
        return self._beyond_model

    @property
    def model_span(self) -> ModelSpan:
        """The model's column space joint by joint, with the filtered residual off it."""
        if self._model_span is None:
            self._model_span = ModelSpan(self.model_cols, self.resid_filtered)
        return self._model_span


def bounds(rows: ProfileRows, blk: Block, hyper: str) -> tuple[float, float]:
    """Where the hyper-parameter may go on the block's side: its grid's span (scaled to
    motor speeds for a motor), and for a ripple any period the data resolves — from the
    smallest catalogued period to half the joint's travel (two cycles seen)."""
    grid = blk.grid(hyper, rows.robot, rows.states.transmission)
    if hyper == "tau_s":  # 1e6 stands for a linear drift, not a time constant to refine to
        return float(min(grid)), float(max(g for g in grid if g < LINEAR_DRIFT))
    if blk.effect.name == "ripple" and blk.joint is not None:
        span = float(np.ptp(rows.states.q[:, blk.joint]))
        return float(min(grid)), max(float(min(grid)) * 2, span / 2)
    return float(min(grid)), float(max(grid))


def profile_effect(rows: ProfileRows, blocks: list[Block], refine: bool = True) -> list[Block]:
    """Choose the free hyper-parameters of one effect on all its candidate joints.

    For each grid value the candidate's columns are evaluated on the profiling rows beyond the
    joint's own friction and model row; the value that explains most of each joint's raw
    residual wins. Several hyper-parameters (Stribeck's velocity and shape) are chosen in
    turn, twice round, each with the others at their last choice. ``refine=False`` stops at
    the grid (``refine_effect`` finishes later, for the candidates that survive the screen).
    """
    free = blocks[0].free_hypers()
    for _ in range(1 if len(free) == 1 else 2):
        for hyper in free:
            blocks = _profile_one(rows, blocks, hyper)
    return refine_effect(rows, blocks) if refine else blocks


def _profile_one(rows: ProfileRows, blocks: list[Block], hyper: str) -> list[Block]:
    """One hyper-parameter of ``blocks`` on its grid (a ripple's period: from the spectrum)."""
    eff = blocks[0].effect
    grids = [np.array(b.grid(hyper, rows.robot, rows.states.transmission)) for b in blocks]
    if eff.name == "ripple":  # the period from the residual's spectrum in q
        chosen = [b.with_opts(**{hyper: _period_from_residual(
            rows.states.q[:, b.joint], rows.resid_filtered[:, b.joint], bounds(rows, b, hyper))})
            for b in blocks]
    elif grids[0].size > 12:  # coarse pass, then the neighbours of each joint's best
        first = _profile_effect_grid(rows, blocks, hyper,
                                     np.stack([g[::4] for g in grids], axis=1))
        picks = [int(np.argmin(np.abs(g - b.opts[hyper]))) for g, b in zip(grids, first,
                                                                          strict=True)]
        values = np.array([[g[min(max(p + k, 0), g.size - 1)] for g, p in zip(grids, picks,
                                                                            strict=True)]
                           for k in range(-4, 5)])
        chosen = _profile_effect_grid(rows, blocks, hyper, values)
    else:
        chosen = _profile_effect_grid(rows, blocks, hyper, np.stack(grids, axis=1))
    return chosen


def refine_effect(rows: ProfileRows, chosen: list[Block]) -> list[Block]:
    """Continuous refinement of each joint's grid choice: a bounded scalar minimisation
    (Brent, in the logarithm) between the choice's grid neighbours, within the bounds; several
    hyper-parameters together (``_refine_jointly``): they trade off along a ridge that one at a
    time stops short on."""
    hypers = [h for h in chosen[0].effect.hypers if h in chosen[0].opts]
    if len(hypers) > 1:
        return [_refine_jointly(rows, b, hypers) for b in chosen]
    for hyper in hypers:
        chosen = _refine_one(rows, chosen, hyper)
    return chosen


def _refine_jointly(rows: ProfileRows, b: Block, hypers: list[str]) -> Block:
    """Several hyper-parameters of a joint's block at once (Stribeck's vs and δ): L-BFGS-B in
    their logarithms from the grid's choice, within their bounds (the grid's span). On their
    ridge, one at a time between grid neighbours stopped short of the optimum (a hidden δ 1
    refined to 0.84 where the optimum lies at 0.98), and a simplex stuck at a bound."""
    span = np.array([bounds(rows, b, h) for h in hypers])  # (hypers, 2)
    box = np.log(span)
    beyond = rows.beyond(b)

    def at(x: np.ndarray) -> Block:  # exp(log(lo)) may round below lo: clipped again
        vals = np.clip(np.exp(np.clip(x, box[:, 0], box[:, 1])), span[:, 0], span[:, 1])
        return b.with_opts(**{h: float(v) for h, v in zip(hypers, vals, strict=True)})

    def cost(x: np.ndarray) -> float:
        return -beyond.share(rows.own_columns(at(x)))

    x0 = np.clip(np.log([float(b.opts[h]) for h in hypers]), box[:, 0], box[:, 1])
    res = minimize(cost, x0, method="L-BFGS-B", bounds=box,
                   options={"ftol": 1e-12, "gtol": 1e-9, "maxiter": 100})
    return at(res.x) if res.fun <= cost(x0) else at(x0)


def _refine_one(rows: ProfileRows, chosen: list[Block], hyper: str) -> list[Block]:
    eff = chosen[0].effect
    out = []
    for b in chosen:
        lo, hi = bounds(rows, b, hyper)
        if hyper == "tau_s" and b.opts[hyper] >= LINEAR_DRIFT:
            out.append(b)  # the linear drift: nothing continuous to refine
            continue
        centre = float(np.clip(b.opts[hyper], lo, hi))
        if eff.name == "ripple":  # the spectral peak's main lobe: ± period / travel
            span = max(float(np.ptp(rows.states.q[:, b.joint])), 1e-9)
            width, tol = float(np.clip(1.0 + 0.5 * centre / span, 1.0005, 1.5)), 1e-5
        else:
            grid = np.array(b.grid(hyper, rows.robot, rows.states.transmission))
            k = int(np.argmin(np.abs(grid - centre)))
            width = max(grid[min(k + 1, grid.size - 1)] / grid[k],
                        grid[k] / grid[max(k - 1, 0)], 1.02)
            tol = 1e-3
        a, z = max(lo, centre / width), min(hi, centre * width)
        if not z > a:
            out.append(b.with_opts(**{hyper: centre}))
            continue
        def cost(logv: float, b: Block = b) -> float:
            trial = b.with_opts(**{hyper: math.exp(logv)})
            if eff.name == "ripple":
                # its period beyond the whole model (its joints' rows bound together, as in
                # the cross-validation): a slow ripple hides in one joint's free model row
                return -float(screens(rows, [trial])[0])
            return -rows.beyond(b).share(rows.own_columns(trial))

        res = minimize_scalar(cost, bounds=(math.log(a), math.log(z)), method="bounded",
                              options={"xatol": tol, "maxiter": 40})
        best = math.exp(float(res.x)) if res.fun <= cost(math.log(centre)) else centre
        out.append(b.with_opts(**{hyper: float(np.clip(best, lo, hi))}))
    return out


def _period_from_residual(q: np.ndarray, r: np.ndarray, span: tuple[float, float]) -> float:
    """Peak of the residual's spectrum against the joint angle, |Σ r·e^(−iωq)|²: q is unevenly
    sampled, so r is summed into bins of q (a twentieth of the shortest period, a phase error
    under 9°) and Fourier-transformed; the refinement finishes the period. ``span``: the
    periods searched (no grid: every period between them the FFT resolves)."""
    pmin, pmax = span
    delta = pmin / 20.0
    k = np.round((q - q.min()) / delta).astype(np.int64)
    binned = np.bincount(k, weights=r - r.mean())
    size = 1 << int(np.ceil(np.log2(max(4 * binned.size, 16.0 * pmax / delta))))
    power = np.abs(np.fft.rfft(binned, min(size, 1 << 22))) ** 2
    nfft = 2 * (power.size - 1)
    idx = np.arange(1, power.size)
    periods = nfft * delta / idx
    ok = (periods >= pmin) & (periods <= pmax)
    if not ok.any():
        return float(np.sqrt(pmin * pmax))
    best = idx[ok][int(np.argmax(power[1:][ok]))]
    return float(nfft * delta / best)


class Beyond:
    """What columns explain of ``y`` beyond a fixed helper block: ``y`` is projected off the
    helpers' basis once, so each trial costs a product with the basis."""

    def __init__(self, basis: np.ndarray, y: np.ndarray) -> None:
        self.u = basis
        self.y = y - basis @ (basis.T @ y)
        self.yy = max(float(y @ y), 1e-300)

    def share(self, cols: np.ndarray) -> float:
        """The share of ``y`` that the columns (N, k) explain beyond the helpers."""
        return float(self.shares([cols])[0])

    def shares(self, trials: Sequence[np.ndarray]) -> np.ndarray:
        """``share`` of each trial's columns (N, k; one k for all) in one projection, the
        least-squares fits on each trial's small Gram at once (minimum norm)."""
        c = np.concatenate(trials, axis=1)
        c = (c - self.u @ (self.u.T @ c)).T.reshape(len(trials), trials[0].shape[1], -1)
        cty = c @ self.y  # (trials, k)
        coef = np.linalg.pinv(c @ c.transpose(0, 2, 1), hermitian=True) @ cty[:, :, None]
        return np.einsum("gk,gk->g", cty, coef[:, :, 0]) / self.yy


def _profile_effect_grid(rows: ProfileRows, blocks: list[Block], hyper: str,
                         values: np.ndarray) -> list[Block]:
    """Score ``values`` (G × blocks: each joint its own candidates), each joint's in one
    projection (``Beyond.shares``). With each candidate the joint's own friction and its row
    of the model are refitted, so the model's parameters cannot hide what the value
    explains."""
    score = np.full(values.shape, -np.inf)
    for bi, b in enumerate(blocks):
        trials = [b.with_opts(**{hyper: float(v)}) for v in values[:, bi]]
        keys = [(t.key, tuple(sorted(t.opts.items()))) for t in trials]
        # a second round meets the first's trials again
        new = {key: t for key, t in zip(keys, trials, strict=True) if key not in rows.tried}
        if new:  # (a global effect: all joints' residual together, ``beyond``)
            shares = rows.beyond(b).shares([rows.own_columns(t) for t in new.values()])
            rows.tried.update(zip(new, map(float, shares), strict=True))
        score[:, bi] = [rows.tried[key] for key in keys]
    best = np.argmax(score, axis=0)
    return [b.with_opts(**{hyper: float(values[best[bi], bi])}) for bi, b in enumerate(blocks)]


def screen(rows: ProfileRows, blk: Block) -> float:
    """In-sample share of the joint's filtered residual (all joints' for a global effect) that
    the candidate removes when added to the model: its columns projected off the model's column
    space against the residual. Cross-validation can only show less, so a candidate under
    SCREEN_MIN is not worth a union column."""
    cols = blk.columns(rows.robot, rows.states)
    resid = rows.resid_filtered
    own = resid if blk.joint is None else resid[:, rows.rows_of(blk)]
    share = rows.beyond_model.share(cols.reshape(-1, cols.shape[2]))
    return share * rows.beyond_model.yy / max(float(np.sum(own * own)), 1e-300)


def screens(rows: ProfileRows, blocks: Sequence[Block]) -> np.ndarray:
    """``screen`` of many candidates at once, on the model's span joint by joint
    (``ModelSpan``): a candidate's columns are non-zero on its own joints' rows only, so it
    is projected there, and what the projection puts on the other joints' rows comes from
    their Grams. Candidates on the same joints share one product."""
    span = rows.model_span
    n = rows.resid_filtered.shape[1]
    groups: dict[tuple[int, ...], list[tuple[int, np.ndarray]]] = {}
    for i, blk in enumerate(blocks):
        joints = rows.rows_of(blk)
        on, own = blk.row_columns(rows.robot, rows.states)
        if on != joints:  # its columns as the effect fills them
            cols = blk.columns(rows.robot, rows.states)
            if len(joints) < n and np.any(np.delete(cols, joints, axis=1)):
                joints = list(range(n))  # not confined to its rows: all of them
            own = cols[:, joints, :]
        groups.setdefault(tuple(joints), []).append((i, own))
    out = np.empty(len(blocks))
    for key, members in groups.items():
        on = list(key)
        cols = np.concatenate([c for _, c in members], axis=2)  # (N, len(on), K)
        own, z = span.project_off(on, cols)
        others = [j for j in range(n) if j not in on]
        g_o, h_o = span.grams[others].sum(axis=0), span.h[others].sum(axis=0)
        y = span.y_perp[:, on].reshape(-1)
        ss = max(float(np.sum(rows.resid_filtered[:, on] ** 2)), 1e-300)
        at = 0
        for i, c in members:
            sl = slice(at, at + c.shape[2])
            at = sl.stop
            o, zc = own[:, :, sl].reshape(-1, c.shape[2]), z[:, sl]
            gram, cty = o.T @ o + zc.T @ g_o @ zc, o.T @ y - zc.T @ h_o
            out[i] = float(cty @ np.linalg.lstsq(gram, cty, rcond=None)[0]) / ss
    return out


class ModelSpan:
    """The model's column space on the profiling rows (joints stacked), joint by joint: a
    joint's rows are non-zero in its own columns only, so the stacked model is factored by a
    QR per joint, stacked and factored again, with the SVD floor of ``basis``; the filtered
    residual projected off it, per joint."""

    def __init__(self, model_cols: np.ndarray, resid: np.ndarray) -> None:
        n_rows, n, p = model_cols.shape
        self.support: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.grams = np.zeros((n, p, p))
        factors = []
        for j in range(n):
            sup = np.flatnonzero(np.abs(model_cols[:, j, :]).max(axis=0) > 0)
            mj = np.ascontiguousarray(model_cols[:, j, sup])
            r = _r_factor(mj)
            full = np.zeros((r.shape[0], p))
            full[:, sup] = r
            factors.append(full)
            self.grams[j] = full.T @ full
            self.support.append(sup)
            self.cols.append(mj)
        r = _r_factor(np.concatenate(factors))
        _, sv, vt = np.linalg.svd(r)
        keep = sv > sv[0] * 1e-10 if sv.size and sv[0] > 0 else np.zeros(sv.size, dtype=bool)
        v = vt[keep].T / sv[keep]
        self.pinv = v @ v.T  # (MᵀM)⁺ on the kept directions
        _, z = self.project_off(list(range(n)), resid[:, :, None])
        self.y_perp = resid - np.stack([m @ z[sup, 0] for sup, m in
                                        zip(self.support, self.cols, strict=True)], axis=1)
        self.h = np.zeros((n, p))
        for j, (sup, m) in enumerate(zip(self.support, self.cols, strict=True)):
            self.h[j, sup] = m.T @ self.y_perp[:, j]

    def project_off(self, joints: list[int], cols: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Columns (N, len(joints), K) confined to ``joints``' rows: what is left of them on
        those rows beyond the model's span, and their coefficients on the model (p, K)."""
        mtc = np.zeros((self.pinv.shape[0], cols.shape[2]))
        for r, j in enumerate(joints):
            mtc[self.support[j]] += self.cols[j].T @ cols[:, r, :]
        z = self.pinv @ mtc
        own = np.stack([cols[:, r, :] - self.cols[j] @ z[self.support[j]]
                        for r, j in enumerate(joints)], axis=1)
        return own, z


def _r_factor(x: np.ndarray) -> np.ndarray:
    """R of x's QR (numpy's mode "r" returns it alone)."""
    return cast(np.ndarray, np.linalg.qr(x, mode="r"))
