"""The one backoff of the link (``link/retry.py``): growth, cap, jitter bounds, and no
hand-written backoff left in the product."""

from __future__ import annotations

import asyncio
import random
import re
from pathlib import Path

import pytest

from robid_link.exceptions import ConfigError
from robid_link.link.retry import Backoff

ROOT = Path(__file__).resolve().parents[2]


def test_the_nominal_delay_doubles_until_the_cap() -> None:
    b = Backoff(0.5, 10.0)
    assert [b.nominal(n) for n in range(1, 8)] == [0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0]
    assert Backoff(1.0, 100.0, factor=3.0).nominal(3) == 9.0


def test_the_cap_holds_for_any_attempt() -> None:
    b = Backoff(0.05, 1.0, factor=10.0)  # 10.0**9999 would overflow a float
    rng = random.Random(1)
    assert all(b.delay(n, rng) <= 1.0 for n in (1, 2, 5, 50, 10_000))
    assert b.nominal(10_000) == 1.0


def test_jitter_stays_between_its_bounds_and_spreads() -> None:
    b = Backoff(2.0, 60.0, jitter=0.5)
    rng = random.Random(7)
    for n in (1, 3, 10):
        d = b.nominal(n)
        got = [b.delay(n, rng) for _ in range(500)]
        assert all(0.5 * d <= x <= d for x in got)
        assert max(got) - min(got) > 0.4 * d  # spread over most of the band
    assert Backoff(2.0, 60.0, jitter=0.0).delay(3, rng) == 8.0


def test_zero_base_never_waits() -> None:
    assert Backoff(0.0, 0.0).delay(5) == 0.0


@pytest.mark.parametrize(("kw", "key"), [
    ({"base_s": -1.0, "cap_s": 1.0}, "base_s"), ({"base_s": 1.0, "cap_s": 0.5}, "cap_s"),
    ({"base_s": 1.0, "cap_s": 2.0, "factor": 0.5}, "factor"),
    ({"base_s": 1.0, "cap_s": 2.0, "jitter": 1.5}, "jitter"),
    ({"base_s": float("nan"), "cap_s": 2.0}, "base_s"), ({"base_s": True, "cap_s": 2.0}, "base_s"),
])
def test_bad_parameters_are_one_line(kw: dict[str, float], key: str) -> None:
    with pytest.raises(ConfigError, match=rf"^backoff\.{key}: expected ") as err:
        Backoff(**kw)
    assert "\n" not in str(err.value)


def test_an_attempt_counts_from_one() -> None:
    with pytest.raises(ValueError, match="counts from 1"):
        Backoff(1.0, 2.0).delay(0)


def test_sleep_waits_the_delay_it_returns() -> None:
    async def go() -> float:
        return await Backoff(0.001, 0.002).sleep(3)

    assert 0.001 <= asyncio.run(go()) <= 0.002


#: what the hand-written backoffs looked like (`delay * random.uniform(0.5, 1.5)`,
#: `backoff_s * 2 ** attempt`, `delay = min(2 * delay, …)`, `delay *= 2`)
_HAND_WRITTEN = re.compile(r"random\.uniform\(|\*\* *\(?(attempt|lost|tries)|"
                           r"delay = min\(2 \* delay|delay \*= ")


def test_no_hand_written_backoff_is_left() -> None:
    files = [p for d in ("robid_link", "drivers") for p in (ROOT / d).rglob("*.py")
             if p.name != "retry.py" and "ident" not in p.parts]
    assert len(files) > 20  # the walk sees the product
    found = [f"{p.relative_to(ROOT)}:{k}" for p in files
             for k, line in enumerate(p.read_text().splitlines(), 1)
             if _HAND_WRITTEN.search(line)]
    assert found == []
