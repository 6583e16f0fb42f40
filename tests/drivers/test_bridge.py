"""The driver base's thread bridge (``link/driver.py``): calls from a driver's thread run on
the loop, a thread that outruns the loop waits for room (bounded), a closed bridge drops calls,
a thread's future is awaited without blocking the loop; the drivers with threads use it."""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from pathlib import Path
from typing import Any

from robid_link.link import registry
from robid_link.link.driver import ThreadBridge


def test_a_call_from_a_thread_runs_on_the_loop() -> None:
    async def go() -> tuple[int, int]:
        bridge = ThreadBridge("t")
        bridge.bind(asyncio.get_running_loop())
        ran = asyncio.Event()
        where: list[int] = []

        def on_loop(x: int) -> None:
            where.append(threading.get_ident())
            ran.set()

        t = threading.Thread(target=bridge.call, args=(on_loop, 1))
        t.start()
        await ran.wait()
        t.join()
        bridge.close()
        return where[0], threading.get_ident()

    on, loop_thread = asyncio.run(go())
    assert on == loop_thread


def test_a_thread_that_outruns_the_loop_waits_for_room() -> None:
    loop = asyncio.new_event_loop()
    try:
        bridge = ThreadBridge("t", maxsize=2)
        bridge.bind(loop)  # bound here, run below: nothing is delivered meanwhile
        got: list[int] = []
        sent: list[int] = []
        two = threading.Event()

        def produce() -> None:
            for k in range(6):
                bridge.call(got.append, k)
                sent.append(k)
                if len(sent) == 2:
                    two.set()

        producer = threading.Thread(target=produce)
        producer.start()
        assert two.wait(10)
        producer.join(0.2)
        assert producer.is_alive() and len(sent) == 2  # blocked on the third: bounded
        while producer.is_alive() or len(got) < 6:  # the loop drains, the producer goes on
            loop.run_until_complete(asyncio.sleep(0.01))
        assert got == list(range(6)) and sent == list(range(6))
    finally:
        loop.close()


def test_a_closed_bridge_drops_calls_and_frees_a_waiting_thread() -> None:
    loop = asyncio.new_event_loop()
    try:
        bridge = ThreadBridge("t", maxsize=1)
        bridge.bind(loop)
        got: list[int] = []
        results: list[bool] = []
        t = threading.Thread(target=lambda: results.extend(bridge.call(got.append, k)
                                                           for k in range(3)))
        t.start()
        t.join(0.2)
        assert t.is_alive()  # waiting for room behind the first call
        bridge.close()
        t.join(5)
        assert not t.is_alive() and results == [True, False, False]
        loop.run_until_complete(asyncio.sleep(0))
        assert got == []  # the queued call is dropped too
        assert bridge.call(got.append, 9) is False
        bridge.close()  # twice is safe
    finally:
        loop.close()


def test_a_thread_future_is_awaited_while_the_loop_ticks() -> None:
    async def go() -> tuple[Any, int]:
        bridge = ThreadBridge("t")
        bridge.bind(asyncio.get_running_loop())
        fut: concurrent.futures.Future[str] = concurrent.futures.Future()
        ticks = 0
        release = threading.Event()

        async def tick() -> None:
            nonlocal ticks
            while True:
                ticks += 1
                if ticks == 5:
                    release.set()
                await asyncio.sleep(0)

        ticker = asyncio.create_task(tick())
        t = threading.Thread(target=lambda: (release.wait(10), fut.set_result("log")))
        t.start()
        try:
            out = await bridge.wait(fut)
        finally:
            ticker.cancel()
            t.join()
        bridge.close()
        done = concurrent.futures.Future[int]()
        done.set_result(3)  # already done: the callback runs on the loop's own thread
        return (out, await bridge.wait(done)), ticks

    out, ticks = asyncio.run(go())
    assert out == ("log", 3) and ticks >= 5


def test_the_driver_owns_its_bridge_and_closes_it_with_itself(tmp_path: Path) -> None:
    """The file share's observer thread reaches the loop through the base's bridge."""
    driver = registry.make_driver({"name": "file_share", "share": str(tmp_path),
                                   "canary_interval_s": 0})

    calls: list[str] = []
    real_call = driver.bridge.call

    def counted(fn: Any, *args: Any) -> bool:
        calls.append(str(args[0]) if args else "")
        return real_call(fn, *args)

    driver.bridge.call = counted  # type: ignore[method-assign]

    async def go() -> bool:
        async with driver:
            assert not driver.bridge.closed
            take = asyncio.create_task(driver.take_done("exp1", "n1", timeout_s=30))
            while not driver._waiters:  # type: ignore[attr-defined]
                await asyncio.sleep(0.01)
            (tmp_path / "sem" / "exp1.n1.done").write_text("0" * 64 + " size=0\n")
            done = await take
            assert done.sha256 == "0" * 64
        await driver.close()  # twice is safe
        return driver.bridge.closed

    assert asyncio.run(go())
    assert "exp1.n1.done" in calls  # the observer thread's event came over the bridge
