"""The candidates a diagnosis scores, and the screens before the union pass: every catalog
effect not in the model on every joint (with a coupled transmission, on the other side too),
hyper-parameters profiled on the residual, one structural QR with the model (absorbed, by
which parameters), and the in-sample screen (can it remove SCREEN_MIN of the residual?)."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from robid_link.ident.diagnosis.hyperparams import (
    ProfileRows,
    profile_effect,
    refine_effect,
    screens,
)
from robid_link.ident.diagnosis.verdict import GAIN_MIN
from robid_link.ident.fit.design import block_columns, random_states
from robid_link.ident.model.effects import REGISTRY, Block, Model, States
from robid_link.ident.model.regressor import BaseSet
from robid_link.ident.model.robot import Robot

__all__ = ["Candidate", "ColumnSpace", "InSample", "Structural", "SCREEN_MIN",
           "catalog_candidates", "coupled_sides", "drop_slow_ripples", "insample_screen",
           "profile_candidates", "refine_survivors", "screen_notes", "structural_screen"]

#: a per-joint candidate is scored only if, in-sample on the profiling rows, it explains this
#: fraction of its joint's filtered residual (≈ half of GAIN_MIN on the RMSE)
SCREEN_MIN = 1.0 - (1.0 - GAIN_MIN / 2) ** 2


def catalog_candidates(robot: Robot, model: Model, default: np.ndarray | None) -> list[Block]:
    """Every catalog effect not in the model, on every joint; with a coupled transmission
    also the other side's friction where the coupling makes it new (joint-side logs: the
    coupled motors'; motor-side logs: the coupled joints' bearings)."""
    blocks = model.blocks(robot)

    def norm(side: str | None) -> str | None:  # a side equal to the logs' is the plain one
        return None if side == ("joint" if default is None else "motor") else side

    present = {(b.effect.name, b.joint, norm(b.side)) for b in blocks}
    present_names = {b.effect.name for b in blocks}

    def taken(name: str, j: int, side: str | None) -> bool:
        return (name, j, side) in present or any(
            (other, j, side) in present for other in REGISTRY
            if name in REGISTRY[other].replaces)

    out = []
    for name, eff in REGISTRY.items():
        if name == "rigid_body" or not eff.catalog:
            continue
        if not eff.per_joint:
            if name not in present_names:
                out.append(Block(eff, None, {}))
            continue
        out += [Block(eff, j, {}) for j in range(robot.n) if not taken(name, j, None)]
    for side, j in coupled_sides(robot, default):
        out += [Block(eff, j, {}, side) for name, eff in REGISTRY.items()
                if eff.sided and not taken(name, j, side)]
    return out


def coupled_sides(robot: Robot, default: np.ndarray | None) -> list[tuple[str, int]]:
    """(side, joint) pairs where a coupled transmission makes the other side's friction new."""
    t_mat = robot.transmission
    if t_mat is None:
        return []
    rows = [m for m in range(robot.n) if np.count_nonzero(t_mat[m]) > 1]
    if default is None:
        return [("motor", m) for m in rows]
    joints = sorted({int(i) for m in rows for i in np.flatnonzero(t_mat[m])})
    return [("joint", i) for i in joints]


def profile_candidates(rows: ProfileRows, candidates: list[Block],
                       aside: Executor | None = None) -> tuple[list[Block], set[str]]:
    """Each effect's free hyper-parameter chosen on its grid, for all its joints at once
    (refined later, for the candidates that survive the screens); and the keys of the
    candidates that had one. Effects are profiled independently: with ``aside`` that executor
    shares the work once it is free — first the joints' bases that every effect reads, then
    the effects (those with several hyper-parameters, two rounds each, first); each thread
    takes the next one left."""
    profiled = {b.key for b in candidates if b.free_hypers()}
    groups = {name: [b for b in candidates if b.effect.name == name]
              for name in sorted({b.effect.name for b in candidates if b.free_hypers()})}
    todo = deque(sorted(groups, key=lambda name: -len(groups[name][0].free_hypers())))
    bases = deque({tuple(rows.rows_of(b)): b for b in candidates if b.free_hypers()
                   and b.joint is not None and b.effect.name != "ripple"}.values())
    left, made = [len(bases)], threading.Condition()

    def drain() -> dict[int, Block]:
        while bases:
            try:
                blk = bases.popleft()
            except IndexError:  # the other thread took the last one
                break
            try:
                rows.beyond(blk)
            finally:  # made or failed (raised here, or by the other's result()): counted
                with made:
                    left[0] -= 1
                    made.notify_all()
        with made:  # every base made, whichever thread made it
            made.wait_for(lambda: left[0] == 0)
        done: dict[int, Block] = {}
        while todo:
            try:
                group = groups[todo.popleft()]
            except IndexError:
                break
            done.update(zip(map(id, group), profile_effect(rows, group, refine=False),
                            strict=True))
        return done

    beside = aside.submit(drain) if aside is not None else None
    chosen = drain()
    if beside is not None and not beside.cancel():  # it started: it finishes its share
        chosen.update(beside.result())
    return [chosen.get(id(b), b) for b in candidates], profiled


def drop_slow_ripples(candidates: list[Block], states: States) -> list[Block]:
    """A "ripple" as slow as the motion (its period over half the joint's travel) is a
    spring's job: not a candidate."""
    span = np.ptp(states.q, axis=0)
    return [b for b in candidates if not (
        b.effect.name == "ripple" and b.opts.get("period", 0.0) > span[b.joint] / 2)]


class ColumnSpace:
    """Which of a candidate's columns add column space to the model (structurally, on the
    same random states as the base set), and which model parameters absorb the rest."""

    def __init__(self, robot: Robot, blocks: Sequence[Block], base: BaseSet,
                 transmission: np.ndarray | None) -> None:
        self.robot = robot
        self.names = list(base.names)
        self.base_names = base.base_names
        n_states = max(200, 4 * len(self.names))
        self.states = random_states(robot, np.random.default_rng(20260), n_states, transmission)
        w = block_columns(robot, blocks, self.states).reshape(-1, len(self.names))
        w = w[:, list(base.independent)]
        self.scale = np.linalg.norm(w, axis=0)
        self.w = w / self.scale
        self.q, _ = np.linalg.qr(self.w)

    def check(self, blk: Block) -> tuple[list[int], list[str]]:
        return self.check_all([blk])[0]

    def check_all(self, blocks: Sequence[Block]) -> list[tuple[list[int], list[str]]]:
        """``check`` of many candidates: their normalized columns projected off the model's
        basis in one product, then each candidate's columns against its own new ones."""
        flat = [c.reshape(-1, c.shape[-1]) for c in
                (blk.columns(self.robot, self.states) for blk in blocks)]
        norms = np.linalg.norm(np.concatenate(flat, axis=1), axis=0)
        v = np.concatenate(flat, axis=1) / np.maximum(norms, 1e-300)
        beyond = v - self.q @ (self.q.T @ v)
        out, at = [], 0
        for wc in flat:
            sl = slice(at, at + wc.shape[1])
            at = sl.stop
            out.append(self._new_columns(wc, norms[sl], v[:, sl], beyond[:, sl]))
        return out

    def _new_columns(self, wc: np.ndarray, norms: np.ndarray, v: np.ndarray,
                     beyond: np.ndarray) -> tuple[list[int], list[str]]:
        if not np.any(norms > 1e-12):
            return [], []  # no column on these states at all: nothing absorbs it
        new: list[int] = []
        extra = np.zeros((wc.shape[0], 0))  # directions of the candidate's new columns
        for i in range(wc.shape[1]):
            if norms[i] <= 1e-12:
                continue
            r = beyond[:, i] - extra @ (extra.T @ v[:, i])
            if np.linalg.norm(r) > 1e-7:
                new.append(i)
                extra = np.column_stack((extra, r / np.linalg.norm(r)))
        by: list[str] = []
        if not new:
            coef, *_ = np.linalg.lstsq(self.w, wc / np.maximum(norms, 1e-300), rcond=None)
            big = np.abs(coef).max(axis=1) > 1e-6
            by = [self.base_names[k] for k in np.flatnonzero(big)]
        return new, by


@dataclass(frozen=True)
class Candidate:
    """A candidate that adds column space to the model: its block, and which of the block's
    columns are new."""

    block: Block
    new: list[int]


@dataclass(frozen=True)
class Structural:
    """The structural screen: candidates with new columns, those the model absorbs (and by
    which of its parameters), and those with no column on the states at all."""

    new: list[Candidate]
    absorbed: list[dict[str, Any]]  # {"effect": key, "by": [base parameter names]}
    silent: list[str]


def structural_screen(robot: Robot, blocks: Sequence[Block], base: BaseSet,
                      transmission: np.ndarray | None, candidates: list[Block]) -> Structural:
    """One QR of the model's base columns (``blocks``, ``base``) on random states; each
    candidate's columns checked against it."""
    space = ColumnSpace(robot, blocks, base, transmission)
    new: list[Candidate] = []
    absorbed: list[dict[str, Any]] = []
    silent: list[str] = []
    for blk, (cols, by) in zip(candidates, space.check_all(candidates), strict=True):
        if cols:
            new.append(Candidate(blk, cols))
        elif by:
            absorbed.append({"effect": blk.key, "by": by})
        else:
            silent.append(blk.key)
    return Structural(new, absorbed, silent)


@dataclass(frozen=True)
class InSample:
    """The in-sample screen: the candidates worth a union column, and how many were not."""

    kept: list[Candidate]
    dropped: int


def insample_screen(rows: ProfileRows, candidates: list[Candidate],
                    made: Mapping[int, float] | None = None) -> InSample:
    """A candidate that cannot explain SCREEN_MIN of its joint's filtered residual even
    in-sample cannot reach GAIN_MIN held out: not worth a union column. ``made``: the
    blocks' screens (``screens``) by id when made already."""
    shares = [made[id(c.block)] for c in candidates] if made is not None else \
        screens(rows, [c.block for c in candidates])
    kept = [c for c, share in zip(candidates, shares, strict=True) if not share < SCREEN_MIN]
    return InSample(kept, len(candidates) - len(kept))


def refine_survivors(rows: ProfileRows, kept: list[Candidate], profiled: set[str],
                     dense: Callable[[], ProfileRows] | None = None) -> list[Candidate]:
    """The profiled hyper-parameters of the candidates left, refined continuously; an
    effect with several (Stribeck's vs and δ, which trade off) on ``dense()``'s rows when
    given: on the profiling rows alone δ's 95 % profile interval spans ±20 %."""
    for name in sorted({c.block.effect.name for c in kept if c.block.key in profiled}):
        group = [c.block for c in kept if c.block.effect.name == name and c.block.key in profiled]
        on = dense() if dense is not None and len(group[0].effect.hypers) > 1 else rows
        fine = dict(zip(map(id, group), refine_effect(on, group), strict=True))
        kept = [replace(c, block=fine[id(c.block)]) if id(c.block) in fine else c
                for c in kept]
    return kept


def screen_notes(structural: Structural, insample: InSample) -> list[str]:
    notes = []
    if structural.silent:
        notes.append(f"{', '.join(structural.silent[:6])}: no column on the data's states at "
                     "any hyper-parameter tried (not scored)")
    if insample.dropped:
        notes.append(f"{insample.dropped} candidate(s) explain under {100 * SCREEN_MIN:.0f} % "
                     "of their joint's filtered residual even in-sample and were not scored")
    return notes
