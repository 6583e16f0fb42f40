"""The regressor assembly: structural base set and sparsity mask, block columns, the compact
design and its parallel-filtered chunks, and the model's predictions on prepared logs.

Everything that turns states into base-regressor rows lives here, so that identify, the
estimators, the diagnosis and the excitation design share one path from log to columns.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np

from robid_link.ident.data.preprocess import CHUNK, Piece, Prepared, filter_windows
from robid_link.ident.model.effects import Block, States
from robid_link.ident.model.regressor import (
    BaseSet,
    preference_order,
    rigid_regressor,
    structural_base_set,
)
from robid_link.ident.model.robot import Robot
from robid_link.ident.model.threads import in_slots

__all__ = [
    "Design",
    "base_set_for",
    "block_columns",
    "design_chunks",
    "design_rows",
    "make_design",
    "predict_torque",
    "random_states",
    "structural_mask",
    "with_predictions",
]


def block_columns(robot: Robot, blocks: Sequence[Block], st: States) -> np.ndarray:
    """(N, n, P): the columns of every block side by side."""
    return np.concatenate([b.columns(robot, st) for b in blocks], axis=2)


def random_states(robot: Robot, rng: np.random.Generator, n: int,
                  transmission: np.ndarray | None = None) -> States:
    """n random states within the joint limits, with every optional input an effect may
    read (time, model torque and its rate): the structural checks see every column."""
    lo = np.where(np.isfinite(robot.limits.q_min), robot.limits.q_min, -math.pi)
    hi = np.where(np.isfinite(robot.limits.q_max), robot.limits.q_max, math.pi)
    q = rng.uniform(lo, hi, (n, robot.n))
    return States(q, rng.normal(size=(n, robot.n)), rng.normal(size=(n, robot.n)),
                  np.sort(rng.uniform(0.0, 100.0, n)), transmission,
                  rng.normal(size=(n, robot.n)), rng.normal(size=(n, robot.n)))


class Design:
    """The model's base columns, evaluated compactly.

    Joint j's torque row is non-zero only in some base columns (its support); the compact
    matrix holds, joint after joint, just those entries: (N, nnz) instead of (N, n, p).
    """

    def __init__(self, robot: Robot, blocks: Sequence[Block], cols: np.ndarray,
                 mask: np.ndarray) -> None:
        self.robot = robot
        self.blocks = tuple(blocks)
        self.cols = np.asarray(cols)
        self.mask = np.asarray(mask, dtype=bool)  # (n, p)
        self.support = [np.flatnonzero(self.mask[j]) for j in range(robot.n)]
        sizes = [s.size for s in self.support]
        self.offsets = np.concatenate(([0], np.cumsum(sizes))).astype(int)
        self._gathers = self._plan()

    @property
    def p(self) -> int:
        return int(self.cols.size)

    @property
    def nnz(self) -> int:
        return int(self.offsets[-1])

    def joint_slice(self, j: int) -> slice:
        return slice(int(self.offsets[j]), int(self.offsets[j + 1]))

    def _plan(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per block: (compact destination columns, flat source index in that block)."""
        widths = [len(b.param_names(self.robot)) for b in self.blocks]
        starts = np.concatenate(([0], np.cumsum(widths))).astype(int)
        plan = []
        for bi, width in enumerate(widths):
            dst, src = [], []
            for j in range(self.robot.n):
                for pos, k in enumerate(self.support[j]):
                    c = int(self.cols[k])
                    if starts[bi] <= c < starts[bi] + width:
                        dst.append(self.offsets[j] + pos)
                        src.append(j * width + c - starts[bi])
            plan.append((np.array(dst, dtype=int), np.array(src, dtype=int)))
        return plan

    def compact(self, st: States, buf: np.ndarray | None = None) -> np.ndarray:
        """(N, nnz) base-column entries of every joint row, joint after joint (in the first
        rows of ``buf`` when given: a pass reuses one buffer)."""
        n_samp = len(st)
        out = np.empty((n_samp, self.nnz)) if buf is None else buf[:n_samp]
        n = self.robot.n
        for blk, (dst, src) in zip(self.blocks, self._gathers, strict=True):
            if dst.size == 0:
                continue
            if blk.effect.name == "rigid_body":  # the kernel writes straight into place
                dest = np.full(n * 10 * n, -1, dtype=np.int64)
                dest[src] = dst
                rigid_regressor(self.robot, st.q, st.qd, st.qdd, out=out,
                                dest=dest.reshape(n, 10 * n))
            else:  # a per-joint block's columns on its own rows only
                rows, vals = blk.row_columns(self.robot, st)
                at = np.full(n, -1)
                at[rows] = np.arange(len(rows))
                width = vals.shape[2]
                pos = at[src // width] * width + src % width
                if np.any(pos < 0):  # structurally non-zero off its rows: the whole block
                    vals, pos = blk.columns(self.robot, st), src
                out[:, dst] = vals.reshape(n_samp, -1)[:, pos]
        return out

    @cached_property
    def fast(self) -> Part | None:
        """The columns of the blocks that are not smooth (``Effect.smooth``: a step at a
        reversal, a position frequency the filter cuts) as a design of their own, with where
        its compact columns sit in this one's; None when every block is smooth."""
        widths = [len(b.param_names(self.robot)) for b in self.blocks]
        smooth = np.repeat([b.effect.smooth for b in self.blocks], widths)
        which = np.flatnonzero(~smooth[self.cols])
        if not which.size:
            return None
        at = [self.offsets[j] + np.flatnonzero(np.isin(self.support[j], which))
              for j in range(self.robot.n)]
        return Part(Design(self.robot, self.blocks, self.cols[which], self.mask[:, which]),
                    which, np.concatenate(at).astype(int))

    def predict(self, c: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Torques (N, n) from compact columns and base parameters."""
        return np.stack([c[:, self.joint_slice(j)] @ theta[self.support[j]]
                         for j in range(self.robot.n)], axis=1)

    def expand(self, c: np.ndarray) -> np.ndarray:
        """(N, n, p) dense base regressor from compact columns."""
        out = np.zeros((c.shape[0], self.robot.n, self.p))
        for j in range(self.robot.n):
            out[:, j, self.support[j]] = c[:, self.joint_slice(j)]
        return out


@dataclass(frozen=True)
class Part:
    """Some of a design's columns as a design of their own (``Design.fast``)."""

    design: Design
    which: np.ndarray  # its columns among the whole design's (θ[which] are its parameters)
    at: np.ndarray  # its compact columns among the whole design's, in order


# ----------------------------------------------------------------------------- base set


def structural_mask(robot: Robot, blocks: Sequence[Block], cols: np.ndarray,
                    transmission: np.ndarray | None = None) -> np.ndarray:
    """(n, len(cols)): where joint j's row of each column can be non-zero (random states)."""
    w = block_columns(robot, blocks,
                      random_states(robot, np.random.default_rng(7), 64, transmission))
    return np.abs(w[:, :, cols]).max(axis=0) > 0


_BASE_SETS: dict[tuple[Any, ...], tuple[Robot, tuple[BaseSet, list[str]]]] = {}


def base_set_for(robot: Robot, blocks: Sequence[Block], transmission: np.ndarray | None = None
                 ) -> tuple[BaseSet, list[str]]:
    """The structural base set of a robot and effect list (random states, fixed seed),
    memoized per robot object: identify, diagnose and excitation ask for the same ones."""
    key = (id(robot), tuple((b.effect.name, b.joint, b.side, tuple(sorted(b.opts.items())))
                            for b in blocks),
           None if transmission is None else transmission.tobytes())
    hit = _BASE_SETS.get(key)
    if hit is not None and hit[0] is robot:
        return hit[1]
    out = _compute_base_set(robot, blocks, transmission)
    if len(_BASE_SETS) >= 64:
        _BASE_SETS.pop(next(iter(_BASE_SETS)))
    _BASE_SETS[key] = (robot, out)  # the reference keeps id(robot) from being reused
    return out


def _compute_base_set(robot: Robot, blocks: Sequence[Block], transmission: np.ndarray | None
                      ) -> tuple[BaseSet, list[str]]:
    names = [nm for b in blocks for nm in b.param_names(robot)]

    def sample(rng: np.random.Generator, n: int) -> np.ndarray:
        w = block_columns(robot, blocks, random_states(robot, rng, n, transmission))
        return w.reshape(-1, w.shape[2])

    rigid = blocks and blocks[0].effect.name == "rigid_body"
    pref = preference_order(robot.n, len(names) - 10 * robot.n) if rigid else None
    return structural_base_set(names, sample, n_samples=max(200, 4 * len(names)),
                               preference=pref), names


def make_design(robot: Robot, blocks: Sequence[Block], transmission: np.ndarray | None = None
                ) -> tuple[Design, BaseSet, list[str]]:
    """Base set plus the structural sparsity of the base columns (random states)."""
    base, names = base_set_for(robot, blocks, transmission)
    cols = np.array(base.independent)
    mask = structural_mask(robot, blocks, cols, transmission)
    return Design(robot, tuple(blocks), cols, mask), base, names


# ----------------------------------------------------------------------------- rows


def design_chunks(design: Design, piece: Piece, interval: int = 1, filtered: bool = True,
                  chunk: int = CHUNK) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Yield (compact columns (m, nnz), τ (m, n), sample index (m,)) for a piece, in chunks.

    With ``filtered`` the columns and the torque are parallel-filtered and decimated by
    ``interval`` (training rows); otherwise columns come from the filtered states at the
    full rate against the raw torques (validation rows).
    """
    prep = piece.prep
    if not filtered:
        for a in range(piece.lo, piece.hi, chunk):
            b = min(a + chunk, piece.hi)
            yield design.compact(prep.states(a, b)), prep.tau[a:b], np.arange(a, b)
        return
    for window in filter_windows(piece, interval, chunk):
        yield design_rows(design, piece, window, interval)


def design_rows(design: Design, piece: Piece, window: tuple[int, int, int, int, bool],
                interval: int = 1, buf: np.ndarray | None = None, smooth: bool = False
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The training rows of one ``filter_windows`` window of a piece: parallel-filtered
    compact columns (in ``buf`` when given), filtered torque and sample index, decimated by
    ``interval``. With ``smooth`` only the columns of the blocks that are not smooth
    (``Design.fast``) are filtered; the smooth ones are read at the kept rows of the filtered
    states as they are (the filter would leave them unchanged: ``interval`` times fewer rows
    to evaluate, nothing of theirs to filter)."""
    a, b, ca, cb, at_edge = window
    prep = piece.prep
    st = prep.states(ca, cb)
    kept = slice(a - ca, b - ca, interval)
    if smooth:
        c = design.compact(st.rows(kept), buf)
        part = design.fast
        if part is not None:
            fast = part.design.compact(st)
            prep.filt.apply_inplace(fast, edges=at_edge)
            c[:, part.at] = fast[kept]
    else:
        c = design.compact(st, buf)
        prep.filt.apply_inplace(c, edges=at_edge)
        c = c[kept]
    return c, prep.tau_f_rows(a, b)[::interval], np.arange(a, b, interval)


def predict_torque(design: Design, prep: Prepared, theta: np.ndarray,
                   chunk: int = CHUNK) -> np.ndarray:
    """The model's torque (N, n) on every sample of a prepared log (unfiltered columns)."""
    n = len(prep.log)
    out = np.zeros((n, design.robot.n))
    for a in range(0, n, chunk):
        b = min(a + chunk, n)
        out[a:b] = design.predict(design.compact(prep.states(a, b)), theta)
    return out


def with_predictions(robot: Robot, preps: Sequence[Prepared], design: Design,
                     theta: np.ndarray, every: int = 1) -> list[Prepared]:
    """The prepared logs with the current model's torque, rigid torque and torque rate on
    every sample (effects that depend on the model's own torque — load friction, delay, the
    diagnosis' candidates — read them); the given ones are left as they are.

    With ``every`` > 1 the smooth blocks' torque (all but ``Design.fast``'s) is evaluated on
    every ``every``-th row of each stretch of the log and a cubic spline is drawn between:
    functions of the filtered states, their content lies far below that rate's Nyquist
    frequency (the diagnosis' rows, ``every`` the rate its Grams are read at). The other
    blocks' torque is evaluated on every row."""
    n_rigid = 10 * robot.n if design.blocks and design.blocks[0].effect.name == "rigid_body" \
        else 0
    part = design.fast if every > 1 else None
    thetas = np.zeros((3, theta.size))  # every column's, the rigid body's, the smooth ones'
    thetas[0] = theta
    rigid = np.asarray(design.cols) < n_rigid
    thetas[1, rigid] = theta[rigid]
    thetas[2] = theta
    if part is not None:
        thetas[2, part.which] = 0.0
    return [_predicted(prep, design, thetas, part, every) for prep in preps]


def _predicted(prep: Prepared, design: Design, thetas: np.ndarray, part: Part | None,
               every: int) -> Prepared:
    """``with_predictions`` of one prepared log."""
    n, n_j = len(prep.log), design.robot.n
    full, rigid = np.zeros((n, n_j)), np.zeros((n, n_j))
    stretches = _stretches(prep, every) if part is not None else []
    nodes = np.concatenate([x for x, _ in stretches]) if stretches else np.zeros(0, int)
    smooth = np.zeros((nodes.size, 2 * n_j))  # the smooth torque and the rigid one there

    def work(a: int, slot: int) -> None:
        b = min(a + CHUNK, n)
        st = prep.states(a, b)
        if part is None:
            c = design.compact(st)
            full[a:b], rigid[a:b] = design.predict(c, thetas[0]), design.predict(c, thetas[1])
            return
        full[a:b] = part.design.predict(part.design.compact(st), thetas[0][part.which])
        at = np.flatnonzero((nodes >= a) & (nodes < b))
        c = design.compact(st.rows(nodes[at] - a))
        smooth[at] = np.hstack((design.predict(c, thetas[2]), design.predict(c, thetas[1])))

    in_slots(range(0, n, CHUNK), work)
    if stretches:
        from scipy.interpolate import CubicSpline

        at = 0
        for x, rows in stretches:
            y = smooth[at: at + x.size]
            at += x.size
            between = CubicSpline(x, y, axis=0)(rows) if x.size < rows.size else y
            full[rows] += between[:, :n_j]
            rigid[rows] = between[:, n_j:]
    return replace(prep, tau_rigid=rigid, tau_model=full,
                   # numpy's stub: a 2-D array's gradient is a pair, axis or not
                   tau_rate=np.gradient(full, 1.0 / prep.filt.fs, axis=0))  # type: ignore[arg-type]


def _stretches(prep: Prepared, every: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The log's filtered segments and the gaps between them, each as (its rows a spline
    runs through: every ``every``-th and the last; its rows), in order. A stretch too short
    for a spline runs through all its rows."""
    n = len(prep.log)
    edges = sorted({0, n, *(e for seg in prep.filtered_segments for e in seg)})
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=False):
        rows = np.arange(a, b)
        x = rows if b - a < 4 * every else np.unique(np.append(rows[::every], b - 1))
        out.append((x, rows))
    return out
