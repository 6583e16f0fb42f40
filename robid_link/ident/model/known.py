"""Known torques of the model file (``known_torque:``): a counterbalance law, a hydraulic
balancer, a cable — torques whose form is known, subtracted before identification.

Each entry is an expression of q1..qn, qd1..qdn, qdd1..qddn and named constants, evaluated
by a small interpreter of Python's ``ast`` (arithmetic and numpy math only: no names, calls
or attributes beyond those listed), or a Python entry point ``module:function`` called as
``function(q, qd, qdd, **constants)`` with (N, n) arrays. Constants listed under ``identify``
must enter the torque linearly: each becomes one regressor column (the torque with that
constant at 1 minus the torque with it at 0), identified with the other parameters.
"""

from __future__ import annotations

import ast
import importlib
import math
import operator
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robid_link.exceptions import ModelError

__all__ = ["KnownTorque", "parse_known_torques", "FUNCTIONS", "known_torque_total"]

#: the functions an expression may call (numpy's, elementwise)
FUNCTIONS: dict[str, Callable[..., Any]] = {
    "sin": np.sin, "cos": np.cos, "tan": np.tan, "arcsin": np.arcsin, "arccos": np.arccos,
    "arctan": np.arctan, "arctan2": np.arctan2, "asin": np.arcsin, "acos": np.arccos,
    "atan": np.arctan, "atan2": np.arctan2, "sinh": np.sinh, "cosh": np.cosh,
    "tanh": np.tanh, "sqrt": np.sqrt, "exp": np.exp, "log": np.log, "log10": np.log10,
    "abs": np.abs, "sign": np.sign, "hypot": np.hypot, "minimum": np.minimum,
    "maximum": np.maximum, "min": np.minimum, "max": np.maximum, "where": np.where,
    "clip": np.clip,
}
_NUMBERS = {"pi": math.pi, "e": math.e}
_BINARY: dict[type, Callable[[Any, Any], Any]] = {
    ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
    ast.Div: operator.truediv, ast.Pow: operator.pow, ast.Mod: np.mod,
}
_UNARY: dict[type, Callable[[Any], Any]] = {ast.UAdd: operator.pos, ast.USub: operator.neg}
_COMPARE: dict[type, Callable[[Any, Any], Any]] = {
    ast.Lt: operator.lt, ast.LtE: operator.le, ast.Gt: operator.gt, ast.GtE: operator.ge,
}
_STATE = re.compile(r"^(q|qd|qdd)([1-9][0-9]*)$")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_KEYS = ("name", "joint", "expression", "function", "constants", "identify", "description")
MAX_EXPRESSION = 2000
MAX_DEPTH = 100  # nesting of the formula's tree (the evaluator recurses)


@dataclass(frozen=True)
class KnownTorque:
    """One ``known_torque`` entry of a model file."""

    name: str
    joint: int | None  # from 1; None: an entry point returning (N, n)
    expression: str | None
    function: str | None  # "module:function"
    constants: tuple[tuple[str, float], ...]
    identify: tuple[str, ...]
    where: str = field(default="known_torque", compare=False)
    raw: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)

    @property
    def label(self) -> str:
        return self.name if self.joint is None else f"{self.name}@{self.joint}"

    def param_names(self) -> list[str]:
        return [f"{c}_{self.name}" for c in self.identify]

    def evaluate(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                 values: Mapping[str, float] | None = None) -> np.ndarray:
        """The torque (N, n) on every joint at these states; ``values`` overrides constants
        (the identified ones default to 0: the fixed part)."""
        consts = {**{c: 0.0 for c in self.identify}, **dict(self.constants), **(values or {})}
        n = q.shape[1]
        with np.errstate(all="ignore"):
            if self.expression is not None:
                env = {f"{k}{j + 1}": a[:, j] for k, a in (("q", q), ("qd", qd), ("qdd", qdd))
                       for j in range(n)}
                out = np.zeros((q.shape[0], n))
                try:
                    val = _Evaluator(env, consts, self.where).run(self.expression)
                    out[:, (self.joint or 1) - 1] = np.broadcast_to(np.asarray(val, float),
                                                                     q.shape[0])
                except (ArithmeticError, ValueError, TypeError) as err:
                    raise ModelError(f"{self.where}.expression ({self.name}): cannot evaluate: "
                                     f"{type(err).__name__}: {str(err)[:80]}") from err
            else:
                out = self._call(q, qd, qdd, consts)
        bad = ~np.isfinite(out)
        if bad.any():
            k = int(np.argwhere(bad)[0][0])
            shown = ", ".join(f"{v:.4g}" for v in q[k])
            raise ModelError(f"{self.where} ({self.name}): the torque is not finite at q = "
                             f"[{shown}] (a square root or logarithm of a negative number, a "
                             "division by zero?)")
        return out

    def _call(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
              consts: dict[str, float]) -> np.ndarray:
        fn = _entry_point(self.function or "", self.where)
        try:
            val = np.asarray(fn(q, qd, qdd, **consts), dtype=float)
        except Exception as err:  # the user's code: any failure is reported, not raised
            raise ModelError(f"{self.where}.function: {self.function} failed: "
                             f"{type(err).__name__}: {str(err)[:120]}") from err
        n = q.shape[1]
        if self.joint is not None and val.shape in ((q.shape[0],), ()):
            out = np.zeros((q.shape[0], n))
            out[:, self.joint - 1] = val
            return out
        if val.shape != (q.shape[0], n):
            want = f"({q.shape[0]},)" if self.joint is not None else f"({q.shape[0]}, {n})"
            raise ModelError(f"{self.where}.function: {self.function} returned shape "
                             f"{val.shape}, expected {want}")
        return val

    def fixed(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """The part known in advance: every identified constant at 0."""
        return self.evaluate(q, qd, qdd)

    def columns(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """(N, n, k): the torque per unit of each identified constant."""
        base = self.fixed(q, qd, qdd)
        cols = [self.evaluate(q, qd, qdd, {c: 1.0}) - base for c in self.identify]
        return np.stack(cols, axis=2) if cols else np.zeros((*base.shape, 0))

    def check(self, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> None:
        """The joints exist, the torque evaluates within the joint limits [lo, hi], and the
        identified constants enter linearly."""
        n = lo.size
        if self.joint is not None and self.joint > n:
            raise ModelError(f"{self.where}.joint: the robot has {n} joints")
        if self.expression is not None:
            for name in _names(_checked_tree(self.expression, self.where)):
                m = _STATE.match(name)
                if m and int(m.group(2)) > n:
                    raise ModelError(f"{self.where}.expression: {name}: the robot has {n} "
                                     "joints")
        if not self.identify:
            return
        q = rng.uniform(lo, hi, (32, n))
        qd, qdd = rng.normal(size=(32, n)), rng.normal(size=(32, n))
        ids = self.identify

        def at(values: dict[str, float]) -> np.ndarray:
            return self.evaluate(q, qd, qdd, values)

        base = at({})
        unit = {c: at({c: 1.0}) - base for c in ids}
        point = {c: float(v) for c, v in zip(ids, rng.uniform(0.5, 2.0, len(ids)), strict=True)}
        f_point = at(point)
        scale = max(float(np.abs(base).max()), float(np.abs(f_point).max()),
                    *(float(np.abs(u).max()) for u in unit.values()), 1e-12)
        tol = 1e-7 * scale
        for c in ids:
            if np.abs(at({c: 2.0}) - base - 2 * unit[c]).max() > tol:
                raise ModelError(f"{self.where}.identify: {c} enters the torque nonlinearly; "
                                 "only constants that multiply a term (or are added) can be "
                                 f"identified: give {c} in constants")
        mixed = [c for c in ids
                 if np.abs(at({**point, c: point[c] + 1.0}) - f_point - unit[c]).max() > tol]
        if mixed:
            raise ModelError(f"{self.where}.identify: {', '.join(mixed)} multiply each other; "
                             "identify their product as one constant instead")
        for c in ids:
            if np.abs(unit[c]).max() <= tol:
                raise ModelError(f"{self.where}.identify: {c} does not change the torque")


def known_torque_total(known: tuple[KnownTorque, ...], q: np.ndarray, qd: np.ndarray,
                       qdd: np.ndarray) -> np.ndarray:
    """The sum of the fixed parts of all known torques (N, n)."""
    out = np.zeros_like(q)
    for kt in known:
        out += kt.fixed(q, qd, qdd)
    return out


# ----------------------------------------------------------------------------- parsing


def _short(x: Any) -> str:
    text = repr(x)
    return text if len(text) <= 40 else text[:37] + "..."


def parse_known_torques(entries: Any, where: str = "known_torque") -> tuple[KnownTorque, ...]:
    if not isinstance(entries, list):
        raise ModelError(f"{where}: expected a list of entries, got {_short(entries)}")
    out = [_parse_one(e, f"{where}[{i}]", i) for i, e in enumerate(entries)]
    names = [kt.name for kt in out]
    for i, nm in enumerate(names):
        if nm in names[:i]:
            raise ModelError(f"{where}[{i}].name: duplicate name {nm!r}")
    return tuple(out)


def _parse_one(e: Any, where: str, index: int) -> KnownTorque:
    if not isinstance(e, dict):
        raise ModelError(f"{where}: expected a mapping (name, joint, expression or function, "
                         f"constants, identify), got {_short(e)}")
    unknown = [k for k in e if k not in _KEYS]
    if unknown:
        raise ModelError(f"{where}: unknown key {str(unknown[0])[:30]!r} (known: "
                         f"{', '.join(sorted(_KEYS))})")
    name = e.get("name", f"known{index + 1}")
    if not isinstance(name, str) or not _NAME.match(name):
        raise ModelError(f"{where}.name: expected a word (letters, digits, _), got "
                         f"{_short(name)}")
    joint = e.get("joint")
    if joint is not None and (isinstance(joint, bool) or not isinstance(joint, int)
                              or joint < 1):
        raise ModelError(f"{where}.joint: expected a joint number from 1, got {_short(joint)}")
    expr, func = e.get("expression"), e.get("function")
    if (expr is None) == (func is None):
        raise ModelError(f"{where}: give one of expression or function")
    consts = _constants(e.get("constants", {}), where)
    ident = e.get("identify", [])
    if not isinstance(ident, list) or not all(isinstance(c, str) for c in ident):
        raise ModelError(f"{where}.identify: expected a list of constant names")
    if len(set(ident)) != len(ident):
        raise ModelError(f"{where}.identify: a constant is listed twice")
    if expr is not None:
        if joint is None:
            raise ModelError(f"{where}.joint: an expression acts on one joint; give joint")
        if not isinstance(expr, str) or not expr.strip() or len(expr) > MAX_EXPRESSION:
            raise ModelError(f"{where}.expression: expected a formula of at most "
                             f"{MAX_EXPRESSION} characters")
        tree = _checked_tree(expr, where)
        free = {nm for nm in _names(tree) if not _STATE.match(nm) and nm not in _NUMBERS}
        missing = sorted(free - set(consts) - set(ident))
        if missing:
            raise ModelError(f"{where}.expression: unknown name {missing[0]!r} (not q1.., "
                             "qd1.., qdd1.., pi, e, nor a constant; give it in constants)")
        unused = sorted(set(ident) - free)
        if unused:
            raise ModelError(f"{where}.identify: {unused[0]!r} does not appear in the "
                             "expression")
    else:
        if not isinstance(func, str) or not re.match(r"^[\w.]+:[\w]+$", func):
            raise ModelError(f"{where}.function: expected 'module:function', got {_short(func)}")
        _entry_point(func, where)
    for c in ident:
        if _STATE.match(c) or c in _NUMBERS:
            raise ModelError(f"{where}.identify: {c!r} is not a constant")
    return KnownTorque(name, joint, expr, func, tuple(sorted(consts.items())), tuple(ident),
                       where, dict(e))


def _constants(x: Any, where: str) -> dict[str, float]:
    if not isinstance(x, dict):
        raise ModelError(f"{where}.constants: expected a mapping name → number")
    out = {}
    for k, v in x.items():
        if not isinstance(k, str) or not _NAME.match(k) or _STATE.match(k) or k in _NUMBERS \
                or k in FUNCTIONS:
            raise ModelError(f"{where}.constants: {_short(k)} cannot name a constant")
        try:
            ok = not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
        except OverflowError:
            ok = False
        if not ok:
            raise ModelError(f"{where}.constants.{k}: expected a finite number, got {_short(v)}")
        out[k] = float(v)
    return out


def _entry_point(spec: str, where: str) -> Callable[..., Any]:
    module, _, attr = spec.partition(":")
    try:
        mod = importlib.import_module(module)
    except Exception as err:  # noqa: BLE001 - the user's module: a bad name, its own errors
        raise ModelError(f"{where}.function: cannot import module {module!r} "
                         f"({type(err).__name__}: {str(err)[:80]})") from err
    try:
        fn = getattr(mod, attr)
    except AttributeError as err:
        raise ModelError(f"{where}.function: module {module!r} has no {attr!r}") from err
    if not callable(fn):
        raise ModelError(f"{where}.function: {spec} is not callable")
    return fn


# ----------------------------------------------------------------------------- expressions

_ALLOWED = (ast.Expression, ast.BinOp, ast.UnaryOp, ast.Call, ast.Name, ast.Constant,
            ast.Load, ast.Compare, *_BINARY, *_UNARY, *_COMPARE)


def _checked_tree(expr: str, where: str) -> ast.Expression:
    try:
        tree = ast.parse(expr.strip(), mode="eval")
    except SyntaxError as err:
        raise ModelError(f"{where}.expression: not a formula ({err.msg} at column "
                         f"{err.offset})") from err
    except (RecursionError, MemoryError) as err:
        raise ModelError(f"{where}.expression: nested too deeply") from err
    depth, stack = 0, list[tuple[ast.AST, int]]([(tree, 1)])
    while stack:  # the evaluator recurses: bound the depth before it runs
        node, d = stack.pop()
        depth = max(depth, d)
        stack += [(child, d + 1) for child in ast.iter_child_nodes(node)]
    if depth > MAX_DEPTH:
        raise ModelError(f"{where}.expression: nested deeper than {MAX_DEPTH} levels")
    for node in ast.walk(tree):
        if not isinstance(node, _ALLOWED):
            raise ModelError(f"{where}.expression: {type(node).__name__} is not allowed "
                             "(only numbers, names, + - * / ** %, comparisons and "
                             f"{', '.join(sorted(FUNCTIONS))})")
        if isinstance(node, ast.Constant) and (isinstance(node.value, bool)
                                               or not isinstance(node.value, int | float)):
            raise ModelError(f"{where}.expression: {_short(node.value)} is not a number")
        if isinstance(node, ast.Call) and (node.keywords or not isinstance(node.func, ast.Name)
                                           or node.func.id not in FUNCTIONS):
            raise ModelError(f"{where}.expression: only calls of {', '.join(sorted(FUNCTIONS))} "
                             "with positional arguments are allowed")
        if isinstance(node, ast.Compare) and len(node.ops) != 1:
            raise ModelError(f"{where}.expression: chained comparisons are not allowed")
    return tree


def _names(tree: ast.AST) -> set[str]:
    called = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and id(n) not in called}


class _Evaluator:
    """Walks a checked tree; nothing reaches Python's eval."""

    def __init__(self, states: dict[str, np.ndarray], consts: Mapping[str, float],
                 where: str) -> None:
        self.env = {**_NUMBERS, **consts, **states}
        self.where = where

    def run(self, expr: str) -> Any:
        return self._node(_checked_tree(expr, self.where).body)

    def _node(self, node: ast.AST) -> Any:
        if isinstance(node, ast.Constant):
            return float(node.value)  # type: ignore[arg-type]  # numbers only (checked)
        if isinstance(node, ast.Name):
            if node.id not in self.env:
                raise ModelError(f"{self.where}.expression: unknown name {node.id!r}")
            return self.env[node.id]
        if isinstance(node, ast.BinOp):
            return _BINARY[type(node.op)](self._node(node.left), self._node(node.right))
        if isinstance(node, ast.UnaryOp):
            return _UNARY[type(node.op)](self._node(node.operand))
        if isinstance(node, ast.Compare):
            return _COMPARE[type(node.ops[0])](self._node(node.left),
                                               self._node(node.comparators[0]))
        if isinstance(node, ast.Call):
            assert isinstance(node.func, ast.Name)
            return FUNCTIONS[node.func.id](*(self._node(a) for a in node.args))
        raise ModelError(f"{self.where}.expression: {type(node).__name__} is not allowed")
