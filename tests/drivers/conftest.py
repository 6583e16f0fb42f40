"""Driver tests: the leak check (threads, asyncio tasks) is the autouse fixture of
``tests/conftest.py``."""
