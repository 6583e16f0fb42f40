"""Choosing a candidate effect's free hyper-parameter (Stribeck velocity, ripple period,
friction exponent, drift time constant …) and screening candidates, on the current model's
residual at a few thousand rows spread over the log — no column is filtered here."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from robid_link.ident.effects import REGISTRY, Block, States
from robid_link.ident.robot import Robot

__all__ = ["profile_effect", "refine_effect", "screen", "basis", "clear_cache"]


def profile_effect(robot: Robot, blocks: list[Block], resid: np.ndarray, states: States,
                   resid_filtered: np.ndarray | None = None,
                   model_cols: np.ndarray | None = None, refine: bool = True) -> list[Block]:
    """Choose the free hyper-parameter of one effect on all its candidate joints.

    For each grid value the candidate's columns are evaluated on the residual's rows
    (``resid`` is the raw torque minus the current model, so no column needs filtering) beyond
    the joint's own friction and model row; the value that explains most of each joint's
    residual wins. ``refine=False`` stops at the grid (``refine_effect`` finishes later, for
    the candidates that survive the screen).
    """
    eff = blocks[0].effect
    hyper = blocks[0].free_hypers()[0]
    full_grid = eff.hypers[hyper].grid
    args = (robot, blocks, resid, states, hyper, model_cols)
    if eff.name == "ripple":  # the period from the residual's spectrum in q
        r = resid if resid_filtered is None else resid_filtered
        chosen = [Block(b.effect, b.joint, {**b.opts, hyper: _period_from_residual(
            states.q[:, b.joint], r[:, b.joint], full_grid)}) for b in blocks]
        return refine_effect(robot, chosen, resid, states, model_cols) if refine else chosen
    if len(full_grid) > 12:  # coarse pass, then the neighbours of each joint's best
        first = _profile_effect_grid(*args, np.tile(np.array(full_grid[::4])[:, None],
                                                    (1, len(blocks))))
        picks = [full_grid.index(b.opts[hyper]) for b in first]
        values = np.array([[full_grid[min(max(p + k, 0), len(full_grid) - 1)] for p in picks]
                           for k in range(-4, 5)])
        chosen = _profile_effect_grid(*args, values)
    else:
        chosen = _profile_effect_grid(*args, np.tile(np.array(full_grid)[:, None],
                                                     (1, len(blocks))))
    return refine_effect(robot, chosen, resid, states, model_cols) if refine else chosen


def refine_effect(robot: Robot, chosen: list[Block], resid: np.ndarray, states: States,
                  model_cols: np.ndarray | None = None) -> list[Block]:
    """Narrowing passes around each joint's grid choice (a ripple's period must be exact)."""
    eff = chosen[0].effect
    hyper = next(h for h in eff.hypers if h in chosen[0].opts)
    args = (robot, chosen, resid, states, hyper, model_cols)
    if eff.name == "ripple":
        return _refine(args, chosen, hyper, np.full(len(chosen), 1.03), passes=3)
    grid = np.array(eff.hypers[hyper].grid)
    width = np.array([grid[min(int(np.argmin(np.abs(grid - b.opts[hyper]))) + 1, grid.size - 1)]
                      / grid[int(np.argmin(np.abs(grid - b.opts[hyper])))] for b in chosen])
    return _refine(args, chosen, hyper, np.maximum(width, 1.02))


def _refine(args: tuple[Any, ...], chosen: list[Block], hyper: str, width: np.ndarray,
            passes: int = 2) -> list[Block]:
    """Narrowing passes of 11 values around each joint's current best."""
    for _ in range(passes):
        centre = np.array([b.opts[hyper] for b in chosen])
        fine = centre[None, :] * width[None, :] ** np.linspace(-1.0, 1.0, 11)[:, None]
        chosen = _profile_effect_grid(*args, fine)
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


def basis(x: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the column space of ``x`` (SVD, relative floor 1e-10)."""
    u, sv, _ = np.linalg.svd(x, full_matrices=False)
    return u[:, sv > sv[0] * 1e-10] if sv.size and sv[0] > 0 else u[:, :0]


class _Beyond:
    """What columns explain of ``y`` beyond a fixed helper block: both are projected off the
    helpers' column space once (SVD), so each trial costs a product with the basis."""

    def __init__(self, basis: np.ndarray, y: np.ndarray) -> None:
        self.u = basis
        self.y = y - basis @ (basis.T @ y)
        self.yy = max(float(y @ y), 1e-300)

    def share(self, cols: np.ndarray) -> float:
        c = cols - self.u @ (self.u.T @ cols)
        cty = c.T @ self.y
        coef = np.linalg.lstsq(c.T @ c, cty, rcond=None)[0]
        return float(cty @ coef) / self.yy


#: helper bases per (states, model columns, joint) of one diagnosis; ``clear_cache`` after it
_BASES: dict[tuple[int, int, int], np.ndarray] = {}


def clear_cache() -> None:
    _BASES.clear()


def _joint_helpers(robot: Robot, states: States, j: int, model_cols: np.ndarray | None
                   ) -> np.ndarray:
    """Orthonormal basis of the joint's own viscous, Coulomb and offset columns and its row of
    the model (memoized for the states and model columns of one diagnosis)."""
    key = (id(states), id(model_cols), j)
    if key in _BASES:
        return _BASES[key]
    parts = [REGISTRY[name].columns(robot, states, j, {})[:, j, :]
             for name in ("viscous", "coulomb", "offset")]
    if model_cols is not None:
        own = model_cols[:, j, :]
        parts.append(own[:, np.abs(own).max(axis=0) > 0])
    _BASES[key] = basis(np.concatenate(parts, axis=1))
    return _BASES[key]


def _profile_effect_grid(robot: Robot, blocks: list[Block], resid: np.ndarray,
                         states: States, hyper: str, model_cols: np.ndarray | None,
                         values: np.ndarray) -> list[Block]:
    """Score ``values`` (G × blocks: each joint its own candidates) in G passes. With each
    candidate the joint's own friction and its row of the model (``model_cols``, dense
    (N, n, p)) are refitted, so the model's parameters cannot hide what the value explains."""
    eff = blocks[0].effect
    score = np.full(values.shape, -np.inf)
    beyond = {b.joint: _Beyond(_joint_helpers(robot, states, b.joint, model_cols),
                               resid[:, b.joint]) for b in blocks if b.joint is not None}
    for gi, row in enumerate(values):
        for bi, (b, v) in enumerate(zip(blocks, row, strict=True)):
            cols = eff.columns(robot, states, b.joint, {**b.opts, hyper: float(v)})
            if b.joint is not None:
                score[gi, bi] = beyond[b.joint].share(cols[:, b.joint, :])
            else:
                score[gi, bi] = _explained(cols.reshape(-1, cols.shape[2]), resid.reshape(-1))
    best = np.argmax(score, axis=0)
    return [Block(b.effect, b.joint, {**b.opts, hyper: float(values[best[bi], bi])})
            for bi, b in enumerate(blocks)]


def _explained(x: np.ndarray, y: np.ndarray) -> float:
    """Fraction of y's sum of squares that least squares on x explains."""
    xty = x.T @ y
    coef = np.linalg.lstsq(x.T @ x, xty, rcond=None)[0]
    return float(xty @ coef) / max(float(y @ y), 1e-300)


def screen(robot: Robot, blk: Block, resid: np.ndarray, states: States,
            model_basis: np.ndarray) -> float:
    """In-sample share of the joint's residual (all joints' for a global effect) that the
    candidate removes when added to the model: its columns projected off the model's column
    space (``model_basis``, joints stacked) against the residual. Cross-validation can only
    show less, so a candidate under SCREEN_MIN is not worth a union column."""
    cols = blk.effect.columns(robot, states, blk.joint, blk.opts)
    c = cols.reshape(-1, cols.shape[2])
    c = c - model_basis @ (model_basis.T @ c)
    y = resid.reshape(-1)
    cty = c.T @ y
    drop = float(cty @ np.linalg.lstsq(c.T @ c, cty, rcond=None)[0])
    own = resid if blk.joint is None else resid[:, blk.joint]
    return drop / max(float(np.sum(own * own)), 1e-300)
