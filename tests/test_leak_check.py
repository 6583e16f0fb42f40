"""The autouse leak check itself (``tests/conftest.py``): a task left pending when its
``asyncio.run`` returns is recorded, a clean run records nothing."""

from __future__ import annotations

import asyncio

from .conftest import _LEAKED_TASKS


def test_a_pending_task_is_recorded() -> None:
    async def main() -> None:
        asyncio.create_task(asyncio.sleep(10), name="left-behind")

    asyncio.run(main())
    found = [t for t in _LEAKED_TASKS if t.startswith("left-behind")]
    _LEAKED_TASKS.clear()  # the leak was on purpose
    assert found


def test_awaited_and_cancelled_tasks_are_not_leaks() -> None:
    async def main() -> None:
        t = asyncio.create_task(asyncio.sleep(10))
        await asyncio.sleep(0)
        t.cancel()
        async with asyncio.TaskGroup() as tg:
            tg.create_task(asyncio.sleep(0))

    asyncio.run(main())
    assert _LEAKED_TASKS == []
