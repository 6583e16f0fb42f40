"""The arm a URScript program drives on the fake UR controller: the motion and register
built-ins of the URScript manual (``servoj``, ``movej``, ``stopj``, ``sleep``, …) turned into one
joint target per controller step, the register writes and text messages on the way."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from robid_link.exceptions import RobidError

__all__ = ["ScriptError", "Machine"]


class ScriptError(RobidError):
    """A program the controller would refuse (syntax) or stop (runtime error)."""


@dataclass
class Machine:
    """What the program does to the arm: ``targets`` (one joint target per controller step of
    ``steptime``), the register writes ``(step, register, value)`` and the text messages.
    ``qd_max`` bounds a servoj target's jump (rad/s): beyond it the arm would protective-stop."""

    q: list[float]
    steptime: float = 0.002
    qd_max: float = 3.2
    max_steps: int = 4_000_000
    targets: list[list[float]] = field(default_factory=list)
    registers: list[tuple[int, int, int]] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)
    idle: int = 0

    def _push(self, q: list[float], steps: int) -> None:
        if len(self.targets) + steps > self.max_steps:
            raise ScriptError(f"program runs longer than {self.max_steps * self.steptime:g} s")
        self.targets.extend([q] * steps)
        self.q = q
        self.idle = 0

    def _joints(self, q: Any, what: str) -> list[float]:
        if not isinstance(q, list) or len(q) != 6 or not all(
                isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
                for x in q):
            raise ScriptError(f"{what}: expected 6 joint positions, got {str(q)[:60]}")
        return [float(x) for x in q]

    # -- built-ins (names and parameters as in the URScript manual)
    def servoj(self, q: Any, a: float = 0.0, v: float = 0.0, t: float = 0.002,
               lookahead_time: float = 0.1, gain: float = 300.0) -> None:
        target = self._joints(q, "servoj")
        if not 0.03 <= lookahead_time <= 0.2 or not 100 <= gain <= 2000:
            raise ScriptError(f"servoj: lookahead_time {lookahead_time} outside [0.03, 0.2] or "
                              f"gain {gain} outside [100, 2000]")
        steps = max(1, round(t / self.steptime))
        jump = max(abs(x - y) for x, y in zip(target, self.q, strict=True))
        if jump > self.qd_max * self.steptime * steps:
            raise ScriptError(f"servoj: target {jump:.4f} rad away from the last one within "
                              f"{steps * self.steptime:g} s: protective stop")
        self._push(target, steps)

    def movej(self, q: Any, a: float = 1.4, v: float = 1.05, t: float = 0.0,
              r: float = 0.0) -> None:
        """A synchronised joint move with a trapezoidal speed profile (speed ``v``,
        acceleration ``a`` on the leading joint)."""
        target = self._joints(q, "movej")
        if not (a > 0 and v > 0):
            raise ScriptError("movej: a and v must be positive")
        start = self.q
        d = max(abs(x - y) for x, y in zip(target, start, strict=True))
        dur = max(d / v + v / a, 1e-9) if d > v * v / a else 2.0 * math.sqrt(d / a)
        dur = max(dur, t)
        n = max(1, math.ceil(dur / self.steptime))
        for k in range(1, n + 1):
            s = _trapezoid(k / n, v * dur / d if d > 0 else 2.0)
            self._push([x0 + s * (x1 - x0) for x0, x1 in zip(start, target, strict=True)], 1)

    def stopj(self, a: float = 2.0) -> None:
        self._push(self.q, 1)

    def sleep(self, t: float) -> None:
        self._push(self.q, max(1, round(t / self.steptime)))

    def sync(self) -> None:
        self._push(self.q, 1)

    def textmsg(self, s1: Any, s2: Any = "") -> None:
        self.messages.append(f"{s1}{s2}")

    def get_steptime(self) -> float:
        return self.steptime

    def write_output_integer_register(self, address: int, value: int) -> None:
        if not (isinstance(address, int) and 0 <= address <= 47 and isinstance(value, int)
                and -2**31 <= value < 2**31):
            raise ScriptError(f"write_output_integer_register({address}, {value}): bad "
                              "address or value")
        self.registers.append((len(self.targets), address, value))

    def get_actual_joint_positions(self) -> list[float]:
        return list(self.q)

    def builtins(self) -> dict[str, Callable[..., Any]]:
        names = ("servoj", "movej", "stopj", "sleep", "sync", "textmsg", "get_steptime",
                 "write_output_integer_register", "get_actual_joint_positions")
        out: dict[str, Callable[..., Any]] = {n: getattr(self, n) for n in names}
        out.update(floor=lambda x: int(math.floor(x)), ceil=lambda x: int(math.ceil(x)),
                   sqrt=math.sqrt, sin=math.sin, cos=math.cos, tan=math.tan,
                   atan2=math.atan2, pow=math.pow, fabs=math.fabs, d2r=math.radians,
                   r2d=math.degrees, get_list_length=len)
        return out


def _trapezoid(x: float, ratio: float) -> float:
    """Normalised position at normalised time ``x`` of a trapezoid whose cruise speed is
    ``ratio`` times the mean speed (2: a triangle)."""
    ratio = min(max(ratio, 1.0 + 1e-9), 2.0)
    ta = 1.0 - 1.0 / ratio  # acceleration share of the time
    if x < ta:
        return 0.5 * ratio * x * x / ta
    if x > 1.0 - ta:
        return 1.0 - 0.5 * ratio * (1.0 - x) ** 2 / ta
    return ratio * (x - 0.5 * ta)
