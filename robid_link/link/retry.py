"""The one retry delay of the link: exponential growth, a cap, and jitter below the nominal
value — the cycle's attempts, reconnects of drivers, a controller's HTTP 503 all wait with it."""

from __future__ import annotations

import asyncio
import math
import random
from dataclasses import dataclass

from robid_link.exceptions import ConfigError

__all__ = ["Backoff"]


@dataclass(frozen=True)
class Backoff:
    """Delays before retries: retry ``n`` (1 = the first) waits between ``(1 - jitter)·d`` and
    ``d`` seconds, ``d = min(cap_s, base_s·factor**(n - 1))``. The delay never exceeds
    ``cap_s``; the jitter spreads the retries of many clients that failed together.

    ``Backoff(0.5, 10).delay(3)`` is in [1, 2]; ``await backoff.sleep(n)`` waits and returns
    the seconds waited.
    """

    base_s: float
    cap_s: float
    factor: float = 2.0
    jitter: float = 0.5

    def __post_init__(self) -> None:
        for key, value, low in (("base_s", self.base_s, 0.0), ("cap_s", self.cap_s, 0.0),
                                ("factor", self.factor, 1.0), ("jitter", self.jitter, 0.0)):
            if (isinstance(value, bool) or not isinstance(value, int | float)
                    or not math.isfinite(value) or value < low):
                raise ConfigError(f"backoff.{key}: expected a finite number >= {low:g}, "
                                  f"got {value!r}")
        if self.jitter > 1:
            raise ConfigError(f"backoff.jitter: expected a fraction in [0, 1], "
                              f"got {self.jitter!r}")
        if self.cap_s < self.base_s:
            raise ConfigError(f"backoff.cap_s: expected at least base_s ({self.base_s:g}), "
                              f"got {self.cap_s!r}")

    def nominal(self, attempt: int) -> float:
        """``d`` of retry ``attempt``: the delay before jitter, capped."""
        if attempt < 1:
            raise ValueError(f"retry attempt counts from 1, got {attempt}")
        if self.base_s == 0 or self.factor == 1:
            return min(self.cap_s, self.base_s)
        # past the cap the power is never computed (10.0**400 overflows a float)
        if attempt - 1 >= math.log(self.cap_s / self.base_s, self.factor):
            return self.cap_s
        return min(self.cap_s, self.base_s * self.factor ** (attempt - 1))

    def delay(self, attempt: int, rng: random.Random | None = None) -> float:
        """Seconds to wait before retry ``attempt`` (1 = the first retry)."""
        d = self.nominal(attempt)
        u = (rng or random).random()
        return d * (1.0 - self.jitter * u)

    async def sleep(self, attempt: int) -> float:
        """Wait the delay of retry ``attempt``; returns the seconds waited."""
        seconds = self.delay(attempt)
        await asyncio.sleep(seconds)
        return seconds
