"""The controller's half of the file names and contents of ``docs/file_share_protocol.md``
(the file-share peer and the fake PLC, whose programs and logs travel on a share), written
from that page: nothing here comes from the daemon's driver."""

from __future__ import annotations

import re
from pathlib import Path

from robid_link.atomic import atomic_write

__all__ = ["SEMAPHORE", "PARAMS_PREFIX", "Share", "parse_semaphore", "done_line"]

#: ``sem/<id>.<n>.<kind>``: ids and nonces of letters, digits, ``_`` and ``-`` (page: Names)
SEMAPHORE = re.compile(r"^([A-Za-z0-9][A-Za-z0-9_-]{0,63})\.([A-Za-z0-9][A-Za-z0-9_-]{0,63})"
                       r"\.(ready|done|failed)$")
#: ids of parameter sets (page: Parameter upload)
PARAMS_PREFIX = "params-"


def parse_semaphore(name: str) -> tuple[str, str, str] | None:
    """``(id, nonce, kind)`` of a semaphore's file name; None for any other name (temporary
    files start with '.', the daemon's canaries too)."""
    m = SEMAPHORE.match(name)
    return (m.group(1), m.group(2), m.group(3)) if m else None


def done_line(sha256: str, size: int) -> bytes:
    """A ``done`` semaphore: the SHA-256 in 64 lower-case hex digits, then ``size=<bytes>``."""
    return f"{sha256.lower()} size={size}\n".encode()


class Share:
    """The four folders of a share and the files a controller reads and writes in them."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.inbox, self.outbox, self.sem, self.params = (self.root / d for d in (
            "inbox", "outbox", "sem", "params"))

    def make(self) -> None:
        for d in (self.inbox, self.outbox, self.sem):
            d.mkdir(parents=True, exist_ok=True)

    def semaphore(self, key: str, nonce: str, kind: str) -> Path:
        return self.sem / f"{key}.{nonce}.{kind}"

    def log(self, key: str, nonce: str) -> Path:
        return self.outbox / f"{key}.{nonce}.log.csv"

    def program(self, key: str) -> tuple[bytes, bytes]:
        """The neutral trajectory ``inbox/<key>.traj.csv`` and its header ``.traj.yaml``."""
        return ((self.inbox / f"{key}.traj.csv").read_bytes(),
                (self.inbox / f"{key}.traj.yaml").read_bytes())

    def parameter_set(self, key: str, nonce: str) -> bytes:
        return (self.params / f"{key}.{nonce}.json").read_bytes()

    def answer_done(self, key: str, nonce: str, sha256: str, size: int) -> None:
        atomic_write(self.semaphore(key, nonce, "done"), done_line(sha256, size))

    def answer_failed(self, key: str, nonce: str, reason: str) -> None:
        text = " ".join(reason.split())[:4000] or "failed"
        atomic_write(self.semaphore(key, nonce, "failed"), f"{text}\n".encode())

    def write_log(self, key: str, nonce: str, data: bytes) -> None:
        """The log, whole (temporary file + rename), before any answer names it."""
        atomic_write(self.log(key, nonce), data)

    def write_partial(self, key: str, nonce: str, data: bytes) -> None:
        """What a controller dying mid-write leaves: a temporary file, never renamed."""
        (self.outbox / f".{key}.{nonce}.log.csv.partial").write_bytes(data)
