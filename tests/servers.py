"""Real servers for the tests, on loopback, started and stopped by the test session: a
PostgreSQL cluster (Debian's postgresql-15: initdb and pg_ctl on a temporary folder and a free
port; as the ``postgres`` user when the tests run as root) and a Dask scheduler with one worker.
Missing binaries skip the tests that need them, with the reason — except in CI (``CI=true``),
where they fail."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

__all__ = ["Postgres", "postgres_server", "DaskCluster", "dask_cluster", "free_port",
           "missing"]

PG_USER = "robid"
PG_PASSWORD = "robid-test-secret"


def missing(reason: str) -> None:
    """Skip with ``reason`` outside CI; in CI the server must run."""
    if os.environ.get("CI") == "true":
        pytest.fail(f"{reason} (CI=true: the server tests must run; .ci/system-deps installs "
                    "it)")
    pytest.skip(reason)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _pg_bin() -> Path | None:
    for version in ("15", "16", "17", "14"):
        folder = Path(f"/usr/lib/postgresql/{version}/bin")
        if (folder / "initdb").is_file() and (folder / "pg_ctl").is_file():
            return folder
    return None


@dataclass
class Postgres:
    """A running cluster: ``url(db)`` (no password: it comes from the PGPASSFILE)."""

    port: int
    folder: Path
    passfile: Path
    created: list[str] = field(default_factory=list)

    def url(self, db: str = "robid") -> str:
        return f"postgresql://{PG_USER}@127.0.0.1:{self.port}/{db}"

    def create_database(self) -> str:
        """A fresh, empty database for one test; its URL."""
        import psycopg

        name = f"robid_t{len(self.created)}_{os.getpid()}"
        with psycopg.connect(host="127.0.0.1", port=self.port, user=PG_USER,
                             password=PG_PASSWORD, dbname="postgres", autocommit=True) as c:
            c.execute(f'CREATE DATABASE "{name}"')
        self.created.append(name)
        return self.url(name)


def _as_owner(cmd: list[str]) -> list[str]:
    """Run as the cluster's owner: ``postgres`` when we are root (initdb refuses root)."""
    return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd


@contextlib.contextmanager
def postgres_server() -> Iterator[Postgres]:
    pg = _pg_bin()
    if pg is None:
        missing("PostgreSQL not installed (/usr/lib/postgresql/15/bin/initdb): apt-get install "
                "postgresql-15")
    assert pg is not None
    try:
        import psycopg  # noqa: F401
    except ImportError:
        missing("psycopg not installed: pip install 'robid_link[fleet]'")
    folder = Path(tempfile.mkdtemp(prefix="robid-pg-"))
    data, sock = folder / "data", folder / "sock"
    sock.mkdir()
    pwfile = folder / "pw"
    pwfile.write_text(PG_PASSWORD + "\n")
    if os.geteuid() == 0:
        shutil.chown(folder, "postgres")
        shutil.chown(sock, "postgres")
        shutil.chown(pwfile, "postgres")
    port = free_port()
    log = folder / "postgres.log"
    subprocess.run(_as_owner([str(pg / "initdb"), "-D", str(data), "-U", PG_USER, "-A",
                              "scram-sha-256", f"--pwfile={pwfile}", "-E", "UTF8",
                              "--no-instructions"]),
                   check=True, capture_output=True, timeout=120)
    if os.geteuid() == 0:
        shutil.chown(folder, "postgres")
    opts = f"-p {port} -h 127.0.0.1 -k {sock} -c max_connections=60 -c shared_buffers=32MB"
    subprocess.run(_as_owner([str(pg / "pg_ctl"), "-D", str(data), "-o", opts, "-l", str(log),
                              "-w", "-t", "60", "start"]),
                   check=True, capture_output=True, timeout=90)
    passfile = folder / "pgpass"
    passfile.write_text(f"127.0.0.1:{port}:*:{PG_USER}:{PG_PASSWORD}\n")
    passfile.chmod(0o600)
    old = os.environ.get("PGPASSFILE")
    os.environ["PGPASSFILE"] = str(passfile)
    try:
        yield Postgres(port, folder, passfile)
    finally:
        if old is None:
            os.environ.pop("PGPASSFILE", None)
        else:
            os.environ["PGPASSFILE"] = old
        subprocess.run(_as_owner([str(pg / "pg_ctl"), "-D", str(data), "-m", "immediate",
                                  "-w", "-t", "60", "stop"]),
                       capture_output=True, timeout=90)
        shutil.rmtree(folder, ignore_errors=True)


# ----------------------------------------------------------------------------------- dask

@dataclass
class DaskCluster:
    address: str
    scheduler_log: Path
    worker_log: Path


def _dask_bin() -> str | None:
    here = Path(sys.executable).parent / "dask"
    return str(here) if here.is_file() else shutil.which("dask")


@contextlib.contextmanager
def dask_cluster(workers: int = 1) -> Iterator[DaskCluster]:
    """``dask scheduler`` and ``dask worker`` processes on loopback (no dashboard)."""
    exe = _dask_bin()
    if exe is None:
        missing("the dask command is not installed: pip install 'robid_link[fleet]'")
    assert exe is not None
    folder = Path(tempfile.mkdtemp(prefix="robid-dask-"))
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    slog, wlog = folder / "scheduler.log", folder / "worker.log"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs: list[subprocess.Popen[bytes]] = []
    try:
        with open(slog, "wb") as out:
            procs.append(subprocess.Popen(
                [exe, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                 "--no-dashboard", "--no-show"], stdout=out, stderr=subprocess.STDOUT, env=env,
                cwd=folder))
        _wait_for(lambda: "Scheduler at" in slog.read_text(errors="replace"), procs[0], slog)
        with open(wlog, "wb") as out:
            procs.append(subprocess.Popen(
                [exe, "worker", address, "--nworkers", str(workers), "--nthreads", "1",
                 "--host", "127.0.0.1", "--no-dashboard", "--local-directory", str(folder),
                 "--name", "robid-test-worker"], stdout=out, stderr=subprocess.STDOUT, env=env,
                cwd=folder))
        _wait_for(lambda: wlog.read_text(errors="replace").count("Registered to")
                  >= workers, procs[1], wlog)
        yield DaskCluster(address, slog, wlog)
    finally:
        for proc in reversed(procs):
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        shutil.rmtree(folder, ignore_errors=True)


def _wait_for(ready: object, proc: subprocess.Popen[bytes], log: Path,
              timeout_s: float = 90.0) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if ready():  # type: ignore[operator]
            return
        if proc.poll() is not None:
            raise AssertionError(f"{proc.args[1]} exited: {log.read_text()[-2000:]}")
        time.sleep(0.1)
    raise AssertionError(f"{proc.args[1]} not ready within {timeout_s} s: "
                         f"{log.read_text()[-2000:]}")
