"""The one rule every driver inherits from the base (``link/driver.py``): anything unexpected
from a hook is one line (ProtocolError once the motion command may have gone out), every call
has a timeout, a log over the cap is refused, the link is checked before a give, and a give
cancelled half-way still ends before its withdraw runs (the race that left a 'ready' on the
share with no run watching it)."""

from __future__ import annotations

import asyncio
import json
import threading
from typing import Any

import pytest

from robid_link.exceptions import ConfigError, DriverError, DriverTimeoutError, ProtocolError
from robid_link.jobs import MotionProgram
from robid_link.link.driver import LINK_OPTIONS, Done, Driver, one_line
from robid_link.link.options import Options, Url


class _Toy(Driver):
    """A controller in memory: ``ready`` holds what was given; hooks misbehave on demand."""

    name = "toy"
    options = Options()

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self.ready: set[tuple[str, str]] = set()
        self.events: list[str] = []
        self.give_delay_s = self.transfer_delay_s = 0.0
        self.wait_answer: Any = None
        self.alive = True

    async def _open(self) -> None: ...

    async def _close(self) -> None: ...

    async def _put_program(self, program: MotionProgram) -> None: ...

    async def _give_ready(self, exp_id: str, nonce: str) -> None:
        def write() -> None:  # a blocking write in a thread: a cancel does not stop it
            threading.Event().wait(self.give_delay_s)
            self.ready.add((exp_id, nonce))
            self.events.append("given")

        await asyncio.to_thread(write)

    async def _wait_done(self, exp_id: str, nonce: str) -> Done:
        answer = self.wait_answer
        if callable(answer):
            return answer()  # type: ignore[no-any-return]
        await asyncio.sleep(3600)
        raise AssertionError

    async def _fetch_logs(self, done: Done) -> bytes:
        await asyncio.sleep(self.transfer_delay_s)  # a controller that trickles its log
        return b"x" * 5000

    async def _withdraw(self, exp_id: str, nonce: str) -> None:
        self.ready.discard((exp_id, nonce))
        self.events.append("withdrawn")

    async def _check_link(self) -> None:
        if not self.alive:
            raise DriverError("toy: heartbeat frozen")


def test_every_driver_has_the_link_options() -> None:
    from robid_link.link import registry

    for name in registry.available_drivers():
        cls = registry.driver_class(name)
        assert set(LINK_OPTIONS) <= set(cls.options), name
    assert _Toy().config.command_timeout_s == 60.0
    with pytest.raises(ConfigError, match=r"driver\.max_log_bytes: expected an integer"):
        _Toy(max_log_bytes="big")


def test_a_give_cancelled_half_way_is_withdrawn_after_it_ends() -> None:
    toy = _Toy()
    toy.give_delay_s = 0.3

    async def go() -> None:
        async with toy:
            giving = asyncio.create_task(toy.give_ready("exp1", "n1"))
            await asyncio.sleep(0.05)  # the thread is writing the 'ready'
            giving.cancel()  # an operator's cancel reaches the run here
            with pytest.raises(asyncio.CancelledError):
                await giving
            await toy.withdraw("exp1", "n1")

    asyncio.run(go())
    assert toy.events == ["given", "withdrawn"]
    assert toy.ready == set()  # nothing left for a controller to run


@pytest.mark.parametrize("answer, words", [
    (lambda: json.loads("<html>"), "JSONDecodeError"),
    (lambda: {}["state"], "KeyError"),
    (lambda: None.get("x"), "AttributeError"),  # type: ignore[union-attr]
])
def test_anything_unexpected_while_taking_is_one_protocol_line(answer: Any, words: str) -> None:
    toy = _Toy()
    toy.wait_answer = answer

    async def go() -> None:
        async with toy:
            await toy.take_done("exp1", "n1", timeout_s=5)

    with pytest.raises(ProtocolError) as err:
        asyncio.run(go())
    line = str(err.value)
    assert line.startswith("toy: take experiment exp1: unexpected from the controller")
    assert words in line and "\n" not in line


def test_a_huge_multi_line_controller_message_becomes_one_short_line() -> None:
    toy = _Toy()

    def answer() -> Done:
        raise DriverError("controller says:\n" + "spam\r\n" * 100_000)

    toy.wait_answer = answer

    async def go() -> None:
        async with toy:
            await toy.take_done("exp1", "n1", timeout_s=5)

    with pytest.raises(DriverError) as err:
        asyncio.run(go())
    assert "\n" not in str(err.value) and len(str(err.value)) <= 400
    assert one_line("a\x00b\tc\n") == "a b c"


def test_calls_have_timeouts_and_logs_a_size_cap() -> None:
    toy = _Toy(command_timeout_s=0.2, max_log_bytes=4096)
    toy.give_delay_s = 1.0

    async def give() -> None:
        async with toy:
            await toy.give_ready("exp1", "n1")

    with pytest.raises(DriverTimeoutError, match=r"give experiment exp1: no answer within "
                                                 r"0\.2 s"):
        asyncio.run(give())

    toy = _Toy(transfer_timeout_s=0.2)
    toy.transfer_delay_s = 5.0

    async def trickle() -> None:
        async with toy:
            await toy.fetch_logs(Done("exp1", "n1", "0" * 64, None))

    with pytest.raises(DriverTimeoutError, match=r"fetch log of experiment exp1: no answer "
                                                 r"within 0\.2 s"):
        asyncio.run(trickle())

    toy = _Toy(max_log_bytes=4096)
    toy.wait_answer = lambda: Done("exp1", "n1", "0" * 64, 1 << 40)

    async def take() -> None:
        async with toy:
            await toy.take_done("exp1", "n1", timeout_s=5)

    with pytest.raises(ProtocolError, match=r"announces a log of 1099511627776 bytes, over "
                                            r"driver\.max_log_bytes \(4096\)"):
        asyncio.run(take())

    toy = _Toy(max_log_bytes=4096)

    async def fetch() -> None:
        async with toy:
            await toy.fetch_logs(Done("exp1", "n1", "0" * 64, None))

    with pytest.raises(ProtocolError, match=r"over driver\.max_log_bytes"):
        asyncio.run(fetch())


def test_the_link_is_checked_before_a_motion_command() -> None:
    toy = _Toy()
    toy.alive = False

    async def go() -> None:
        async with toy:
            await toy.give_ready("exp1", "n1")

    with pytest.raises(DriverError, match="heartbeat frozen"):
        asyncio.run(go())
    assert toy.ready == set()


def test_a_url_with_credentials_is_refused_without_showing_them() -> None:
    url = Url()
    with pytest.raises(ConfigError) as err:
        url.convert("driver.url", "https://admin:s3cret@10.0.0.1")
    assert "s3cret" not in str(err.value) and "admin" not in str(err.value)
    assert "credentials in the URL are refused" in str(err.value)
    with pytest.raises(ConfigError) as err:
        url.convert("driver.url", "ftp://admin:s3cret@10.0.0.1/x")
    assert "s3cret" not in str(err.value)
    assert url.convert("driver.url", "https://10.0.0.1:8443/") == "https://10.0.0.1:8443"
    with pytest.raises(ConfigError, match="driver.url: expected http|https://host"):
        url.convert("driver.url", "https://10.0.0.1/rw")
