"""What a daemon config needs besides valid keys, checked alike by ``robid config check`` and the
daemon's start: every path it names (exists, readable or writable as needed, not a FIFO or a
device) and each campaign's model and experiment files; and which model file changed since.

A finding is one line naming the key and the path. ``campaign`` None: the daemon cannot work
(it refuses to start); a campaign's name: that campaign's runs will be refused (the daemon
starts and warns).
"""

from __future__ import annotations

import errno
import hashlib
import os
import stat
import tempfile
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robid_link.config import DaemonConfig
from robid_link.link.options import File, Folder, Option
from robid_link.safeopen import file_problem

__all__ = ["Finding", "daemon_findings", "campaign_findings", "ModelWatch", "SOCKET_PATH_MAX"]

#: the longest path a Unix socket can bind to (sun_path holds 108 bytes with its NUL)
SOCKET_PATH_MAX = 107
#: a model file is a few kB; a bigger one is not hashed
_MODEL_BYTES = 4 * 1024 * 1024


@dataclass(frozen=True)
class Finding:
    """One problem of the config: ``key`` its path (``state_dir``, ``campaigns.a.model``),
    ``line`` the sentence naming key, file and problem; ``campaign`` whose runs it stops
    (None: the whole daemon)."""

    key: str
    line: str
    campaign: str | None = None


def _readable(path: Path, what: str) -> str | None:
    """Why ``path`` cannot be read as a regular file (``what`` names it), or None."""
    problem = file_problem(path)
    if problem:
        return f"{what} {problem}"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as err:
        return f"{what} cannot be read ({err.strerror or err}{_as_whom(err)})"
    os.close(fd)
    return None


def _writable_folder(path: Path) -> str | None:
    """Why the daemon cannot make files in the folder ``path`` (created with its parents when
    missing), or None: a probe file is made, since root passes every ``os.access``."""
    existing = path
    while not os.path.lexists(existing) and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return ("is not a folder" if existing == path
                else f"cannot be created: {existing} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".robid-probe-")
    except OSError as err:  # as whom: config check may run as another user than the daemon
        reason = f"{err.strerror or err}{_as_whom(err)}"
        return (f"cannot write in it ({reason})" if existing == path
                else f"cannot be created: cannot write in {existing} ({reason})")
    os.close(fd)
    os.unlink(probe)
    return None


def _as_whom(err: OSError) -> str:
    """For a permission error: the user the check ran as (the daemon's may differ)."""
    if err.errno not in (errno.EACCES, errno.EPERM):
        return ""
    try:
        import pwd

        return f", as user {pwd.getpwuid(os.geteuid()).pw_name}"
    except (ImportError, KeyError):
        return f", as uid {os.geteuid()}"


def _socket_problem(path: Path) -> str | None:
    if len(os.fsencode(path)) > SOCKET_PATH_MAX:
        return (f"{len(os.fsencode(path))} bytes long, more than the {SOCKET_PATH_MAX} a Unix "
                "socket path can have")
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):  # the folder is checked below
        mode = None
    except OSError as err:
        return f"cannot be looked at ({err.strerror or err})"
    if mode is not None and not stat.S_ISSOCK(mode):
        return "exists and is not a socket (the daemon never replaces it)"
    folder = _writable_folder(path.parent)
    return f"its folder {path.parent} {folder}" if folder else None


def _option_paths(options: Mapping[str, Option], given: Mapping[str, Any]
                  ) -> list[tuple[str, Path, Option]]:
    return [(key, Path(str(given[key])), spec) for key, spec in options.items()
            if isinstance(spec, File | Folder) and isinstance(given.get(key), str)
            and given[key]]


def daemon_findings(cfg: DaemonConfig,
                    driver_options: Mapping[str, Option] | Collection[str] | None = None
                    ) -> list[Finding]:
    """The paths the whole daemon needs: the robot file, the state_dir and a log_store folder
    (writable), the control socket (its folder writable, nothing else in its place) and the
    driver's files and folders (``driver_options``: the driver class's ``options``; a plain
    set of names declares none)."""
    out = []
    problem = _readable(cfg.robot, "robot description")
    if problem:
        out.append(Finding("robot", f"robot: {cfg.robot}: {problem}"))
    problem = _writable_folder(cfg.state_dir)
    if problem:
        out.append(Finding("state_dir", f"state_dir: {cfg.state_dir}: {problem}"))
    if cfg.log_store and "://" not in cfg.log_store:  # a URL is reached at the first log
        problem = _writable_folder(Path(cfg.log_store))
        if problem:
            out.append(Finding("log_store", f"log_store: {cfg.log_store}: {problem}"))
    problem = _socket_problem(cfg.control_socket)
    if problem:
        out.append(Finding("control_socket", f"control_socket: {cfg.control_socket}: {problem}"))
    # a plug-in may still declare its options as a set of names: no paths known then
    specs = driver_options if isinstance(driver_options, Mapping) else {}
    for key, path, spec in _option_paths(specs, cfg.driver):
        if isinstance(spec, File):
            problem = _readable(path, "file")
        elif not path.is_dir() and not (isinstance(spec, Folder) and spec.created):
            problem = "folder not found" if not os.path.lexists(path) else "is not a folder"
        else:  # there, or made by the driver: files can be written in it
            problem = _writable_folder(path)
        if problem:
            out.append(Finding(f"driver.{key}", f"driver.{key}: {path}: {problem}"))
    return out


def campaign_findings(cfg: DaemonConfig, name: str) -> list[Finding]:
    """The files a run of campaign ``name`` reads: its model file, each custom experiment's
    trajectory (CSV and its .yaml header)."""
    camp = cfg.campaigns[name]
    out = []
    if camp.model is not None:
        problem = _readable(camp.model, "model file")
        if problem:
            out.append(Finding(f"campaigns.{name}.model",
                               f"campaigns.{name}.model: {camp.model}: {problem}", name))
    for exp in camp.experiments:
        if exp.kind != "custom":
            continue
        csv = Path(str(exp.options["trajectory"])).expanduser()
        csv = csv if csv.is_absolute() else cfg.base_dir / csv
        key = f"campaigns.{name}.experiments.{exp.exp_id}.trajectory"
        for path, what in ((csv, "trajectory file"), (csv.with_suffix(".yaml"),
                                                      "trajectory header")):
            problem = _readable(path, what)
            if problem:
                out.append(Finding(key, f"{key}: {path}: {problem}", name))
                break
    return out


class ModelWatch:
    """The campaigns' model files as the daemon last read them: a run that finds its model
    file edited since says so in one log line (and identifies with the new model)."""

    def __init__(self) -> None:
        self._seen: dict[str, str] = {}

    def seen(self, cfg: DaemonConfig, name: str, effects: tuple[str, ...] = ()) -> str | None:
        """Note campaign ``name``'s model file now; the line to log when it changed."""
        model = cfg.campaigns[name].model
        if model is None:
            return None
        try:
            with open(model, "rb") as fh:
                digest = hashlib.sha256(fh.read(_MODEL_BYTES)).hexdigest()
        except OSError:
            return None  # the model check says what is wrong with it
        before, self._seen[name] = self._seen.get(name), digest
        if before is None or before == digest:
            return None
        now = f" [{', '.join(effects)}]" if effects else ""
        return (f"campaign {name}: model file {model} changed since it was last read (sha256 "
                f"{before[:12]} → {digest[:12]}): reloaded, this run identifies with it{now}")
