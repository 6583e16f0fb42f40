"""Where the fleet's tasks run: a Dask cluster (``Client()``, a LocalCluster, when no scheduler
is named; ``Client(address)`` otherwise) or this process, one task after another (the page's
JSON, tests of the task code). The task code is the same on all three."""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from robid_link.exceptions import ConfigError, RobidError

__all__ = ["Engine", "InlineEngine", "DaskEngine", "make_engine"]


class Engine:
    """``submit(fn, *args)`` → a future (args may hold futures of earlier tasks, in lists),
    ``gather(futures)``, ``as_completed(futures)`` → (future, result); ``describe()`` says
    where the tasks ran."""

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        raise NotImplementedError

    def gather(self, futures: Sequence[Any]) -> list[Any]:
        raise NotImplementedError

    def as_completed(self, futures: Sequence[Any]) -> Iterator[tuple[Any, Any]]:
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        raise NotImplementedError

    def close(self) -> None:
        """Release the cluster (safe twice)."""

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Done:
    def __init__(self, value: Any) -> None:
        self.value = value


def _resolve(arg: Any) -> Any:
    if isinstance(arg, _Done):
        return arg.value
    if isinstance(arg, list | tuple):
        return type(arg)(_resolve(a) for a in arg)
    if isinstance(arg, dict):
        return {k: _resolve(v) for k, v in arg.items()}
    return arg


class InlineEngine(Engine):
    """Each task runs here when submitted."""

    def __init__(self) -> None:
        self.tasks = 0

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        self.tasks += 1
        return _Done(fn(*_resolve(list(args))))

    def gather(self, futures: Sequence[Any]) -> list[Any]:
        return [f.value for f in futures]

    def as_completed(self, futures: Sequence[Any]) -> Iterator[tuple[Any, Any]]:
        for f in futures:
            yield f, f.value

    def describe(self) -> dict[str, Any]:
        return {"engine": "inline", "tasks": self.tasks}


class DaskEngine(Engine):
    """A ``distributed.Client``: of a LocalCluster (``workers`` processes, one thread each)
    or of the scheduler at ``address``."""

    def __init__(self, address: str | None = None, workers: int | None = None,
                 timeout_s: float = 30.0) -> None:
        try:
            from distributed import Client
        except ImportError as err:
            raise ConfigError("robid fleet needs the extra 'fleet' (pip install "
                              "'robid_link[fleet]')") from err
        self.address = address
        try:
            if address:
                self.client = Client(address, timeout=timeout_s)
            else:
                self.client = Client(n_workers=workers, threads_per_worker=1, processes=True,
                                     dashboard_address=None)
        except (OSError, TimeoutError) as err:
            where = address or "a local cluster"
            raise RobidError(f"--scheduler {where}: cannot connect ({err})") from err
        self.tasks = 0

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        # a key of our own: hashing the rows for a content key costs more than the task
        self.tasks += 1
        return self.client.submit(fn, *args, key=f"{fn.__name__}-{uuid.uuid4().hex}")

    def gather(self, futures: Sequence[Any]) -> list[Any]:
        return list(self.client.gather(list(futures)))

    def as_completed(self, futures: Sequence[Any]) -> Iterator[tuple[Any, Any]]:
        from distributed import as_completed

        yield from as_completed(list(futures), with_results=True)

    def describe(self) -> dict[str, Any]:
        info = self.client.scheduler_info()
        return {"engine": "dask", "scheduler": self.client.scheduler.address,
                "local_cluster": self.address is None, "workers": len(info.get("workers", {})),
                "tasks": self.tasks}

    def close(self) -> None:
        import logging

        client = getattr(self, "client", None)
        if client is None:
            return
        self.client = None  # type: ignore[assignment]
        cluster = client.cluster
        quiet = logging.getLogger("distributed")
        level = quiet.level
        quiet.setLevel(logging.CRITICAL)  # a local worker's last heartbeat races the shutdown
        try:
            client.close()
            if cluster is not None:
                cluster.close()
        finally:
            quiet.setLevel(level)


def make_engine(scheduler: str | None, workers: int | None = None) -> Engine:
    """Dask: the named scheduler (``tcp://HOST:PORT``), else a LocalCluster."""
    return DaskEngine(scheduler, workers)
