"""Reading files a controller (or anyone with write access to the share) put there: never
through a link, only regular files, never more than a size limit, never on the event loop."""

from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["read_regular", "describe", "file_problem", "NotRegularError",
           "TooLargeError"]


class NotRegularError(OSError):
    """A symlink, FIFO, device, socket or folder where a regular file was expected."""


class TooLargeError(OSError):
    """A file larger than the limit its reader allows."""


def read_regular(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The bytes of ``path``: opened without following a final symlink and without blocking
    on a FIFO, refused unless a regular file of at most ``max_bytes`` bytes. Blocking (file
    I/O): call it through ``asyncio.to_thread`` from async code."""
    flags = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
    try:
        fd = os.open(path, flags)
    except OSError as err:
        if err.errno == 40:  # ELOOP: the final component is a symlink
            raise NotRegularError(err.errno, "a symbolic link, not a regular file",
                                  str(path)) from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotRegularError(0, "not a regular file", str(path))
        if st.st_size > max_bytes:
            raise TooLargeError(0, f"{st.st_size} bytes, more than the {max_bytes} allowed",
                                str(path))
        chunks, left = [], max_bytes + 1  # a file growing while read is still bounded
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        data = b"".join(chunks)
        if len(data) > max_bytes:
            raise TooLargeError(0, f"more than the {max_bytes} bytes allowed", str(path))
        return data
    finally:
        os.close(fd)


def describe(err: OSError, path: str | os.PathLike[str]) -> str:
    """One line for an error of :func:`read_regular`."""
    return f"{Path(path)}: {err.strerror or err}"


_KINDS = ((stat.S_ISDIR, "is a folder, not a file"), (stat.S_ISFIFO, "is a FIFO"),
          (stat.S_ISCHR, "is a character device"), (stat.S_ISBLK, "is a block device"),
          (stat.S_ISSOCK, "is a socket"))


def file_problem(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` (followed through links) is not a regular file a command can read, as the
    end of a sentence naming it (``not found``, ``is a folder, not a file``, ``is a FIFO, not
    a regular file``), or None. A FIFO would block the reader, a device never end."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return "not found"
    except OSError as err:
        return f"cannot be read ({err.strerror or err})"
    if stat.S_ISREG(mode):
        return None
    for test, text in _KINDS:
        if test(mode):
            return text if test is stat.S_ISDIR else f"{text}, not a regular file"
    return "is not a regular file"
