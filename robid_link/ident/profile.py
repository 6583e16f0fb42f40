"""Choosing a candidate effect's free hyper-parameter (Stribeck velocity, ripple period,
friction exponent, drift time constant …) and screening candidates, on the current model's
residual at a few thousand rows spread over the log — no column is filtered here."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from robid_link.ident.effects import REGISTRY, Block, States
from robid_link.ident.robot import Robot

__all__ = ["ProfileRows", "profile_effect", "refine_effect", "screen", "basis"]


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
    _helpers: dict[int, np.ndarray] = field(default_factory=dict, repr=False)
    _beyond_model: _Beyond | None = field(default=None, repr=False)

    def helper_basis(self, j: int) -> np.ndarray:
        """Basis of joint j's own viscous, Coulomb and offset columns and its model row."""
        if j not in self._helpers:
            parts = [REGISTRY[name].columns(self.robot, self.states, j, {})[:, j, :]
                     for name in ("viscous", "coulomb", "offset")]
            own = self.model_cols[:, j, :]
            parts.append(own[:, np.abs(own).max(axis=0) > 0])
            self._helpers[j] = basis(np.concatenate(parts, axis=1))
        return self._helpers[j]

    @property
    def beyond_model(self) -> _Beyond:
        """The filtered residual (joints stacked) projected off the model's column space."""
        if self._beyond_model is None:
            model = basis(self.model_cols.reshape(-1, self.model_cols.shape[2]))
            self._beyond_model = _Beyond(model, self.resid_filtered.reshape(-1))
        return self._beyond_model


def profile_effect(rows: ProfileRows, blocks: list[Block], refine: bool = True) -> list[Block]:
    """Choose the free hyper-parameter of one effect on all its candidate joints.

    For each grid value the candidate's columns are evaluated on the profiling rows beyond the
    joint's own friction and model row; the value that explains most of each joint's raw
    residual wins. ``refine=False`` stops at the grid (``refine_effect`` finishes later, for
    the candidates that survive the screen).
    """
    eff = blocks[0].effect
    hyper = blocks[0].free_hypers()[0]
    full_grid = eff.hypers[hyper].grid
    if eff.name == "ripple":  # the period from the residual's spectrum in q
        chosen = [Block(b.effect, b.joint, {**b.opts, hyper: _period_from_residual(
            rows.states.q[:, b.joint], rows.resid_filtered[:, b.joint], full_grid)})
            for b in blocks]
    elif len(full_grid) > 12:  # coarse pass, then the neighbours of each joint's best
        first = _profile_effect_grid(rows, blocks, hyper, np.tile(
            np.array(full_grid[::4])[:, None], (1, len(blocks))))
        picks = [full_grid.index(b.opts[hyper]) for b in first]
        values = np.array([[full_grid[min(max(p + k, 0), len(full_grid) - 1)] for p in picks]
                           for k in range(-4, 5)])
        chosen = _profile_effect_grid(rows, blocks, hyper, values)
    else:
        chosen = _profile_effect_grid(rows, blocks, hyper, np.tile(
            np.array(full_grid)[:, None], (1, len(blocks))))
    return refine_effect(rows, chosen) if refine else chosen


def refine_effect(rows: ProfileRows, chosen: list[Block]) -> list[Block]:
    """Narrowing passes around each joint's grid choice (a ripple's period must be exact)."""
    eff = chosen[0].effect
    hyper = next(h for h in eff.hypers if h in chosen[0].opts)
    if eff.name == "ripple":
        return _refine(rows, chosen, hyper, np.full(len(chosen), 1.03), passes=3)
    grid = np.array(eff.hypers[hyper].grid)
    width = np.array([grid[min(int(np.argmin(np.abs(grid - b.opts[hyper]))) + 1, grid.size - 1)]
                      / grid[int(np.argmin(np.abs(grid - b.opts[hyper])))] for b in chosen])
    return _refine(rows, chosen, hyper, np.maximum(width, 1.02))


def _refine(rows: ProfileRows, chosen: list[Block], hyper: str, width: np.ndarray,
            passes: int = 2) -> list[Block]:
    """Narrowing passes of 11 values around each joint's current best."""
    for _ in range(passes):
        centre = np.array([b.opts[hyper] for b in chosen])
        fine = centre[None, :] * width[None, :] ** np.linspace(-1.0, 1.0, 11)[:, None]
        chosen = _profile_effect_grid(rows, chosen, hyper, fine)
        width = width ** 0.2
    return chosen


def _period_from_residual(q: np.ndarray, r: np.ndarray, grid: Sequence[float]) -> float:
    """Peak of the residual's spectrum against the joint angle, |Σ r·e^(−iωq)|²: q is unevenly
    sampled, so r is summed into bins of q (a twentieth of the shortest period, a phase error
    under 9°) and Fourier-transformed; the refinement passes finish the period."""
    pmin, pmax = float(min(grid)), float(max(grid))
    delta = pmin / 20.0
    k = np.round((q - q.min()) / delta).astype(np.int64)
    binned = np.bincount(k, weights=r - r.mean())
    size = 1 << int(np.ceil(np.log2(max(4 * binned.size, 64.0 * pmax / delta))))
    power = np.abs(np.fft.rfft(binned, min(size, 1 << 22))) ** 2
    nfft = 2 * (power.size - 1)
    idx = np.arange(1, power.size)
    periods = nfft * delta / idx
    ok = (periods >= pmin) & (periods <= pmax)
    if not ok.any():
        return float(np.sqrt(pmin * pmax))
    best = idx[ok][int(np.argmax(power[1:][ok]))]
    return float(nfft * delta / best)


class _Beyond:
    """What columns explain of ``y`` beyond a fixed helper block: ``y`` is projected off the
    helpers' basis once, so each trial costs a product with the basis."""

    def __init__(self, basis: np.ndarray, y: np.ndarray) -> None:
        self.u = basis
        self.y = y - basis @ (basis.T @ y)
        self.yy = max(float(y @ y), 1e-300)

    def share(self, cols: np.ndarray) -> float:
        c = cols - self.u @ (self.u.T @ cols)
        cty = c.T @ self.y
        coef = np.linalg.lstsq(c.T @ c, cty, rcond=None)[0]
        return float(cty @ coef) / self.yy


def _profile_effect_grid(rows: ProfileRows, blocks: list[Block], hyper: str,
                         values: np.ndarray) -> list[Block]:
    """Score ``values`` (G × blocks: each joint its own candidates) in G passes. With each
    candidate the joint's own friction and its row of the model are refitted, so the model's
    parameters cannot hide what the value explains."""
    eff = blocks[0].effect
    score = np.full(values.shape, -np.inf)
    no_helpers = np.zeros((rows.resid.size, 0))
    beyond = {b.joint: _Beyond(rows.helper_basis(b.joint), rows.resid[:, b.joint])
              for b in blocks if b.joint is not None}
    for gi, row in enumerate(values):
        for bi, (b, v) in enumerate(zip(blocks, row, strict=True)):
            cols = eff.columns(rows.robot, rows.states, b.joint, {**b.opts, hyper: float(v)})
            if b.joint is not None:
                score[gi, bi] = beyond[b.joint].share(cols[:, b.joint, :])
            else:  # a global effect: all joints' residual together
                score[gi, bi] = _Beyond(no_helpers, rows.resid.reshape(-1)).share(
                    cols.reshape(-1, cols.shape[2]))
    best = np.argmax(score, axis=0)
    return [Block(b.effect, b.joint, {**b.opts, hyper: float(values[best[bi], bi])})
            for bi, b in enumerate(blocks)]


def screen(rows: ProfileRows, blk: Block) -> float:
    """In-sample share of the joint's filtered residual (all joints' for a global effect) that
    the candidate removes when added to the model: its columns projected off the model's column
    space against the residual. Cross-validation can only show less, so a candidate under
    SCREEN_MIN is not worth a union column."""
    cols = blk.effect.columns(rows.robot, rows.states, blk.joint, blk.opts)
    resid = rows.resid_filtered
    own = resid if blk.joint is None else resid[:, blk.joint]
    share = rows.beyond_model.share(cols.reshape(-1, cols.shape[2]))
    return share * rows.beyond_model.yy / max(float(np.sum(own * own)), 1e-300)
