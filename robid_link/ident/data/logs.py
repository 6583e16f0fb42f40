"""Log files (CSV, npz, FDURoID .mat, ROS bags) → checked, uniformly sampled joint-side logs.

Every bad input raises a one-line :class:`DataError` naming the file and the problem.
"""

from __future__ import annotations

import csv
import hashlib
import math
import threading
import warnings
import zipfile
import zlib
from collections.abc import Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.exceptions import DataError, DataWarning, RobidError
from robid_link.ident.data.bags import is_bag, read_bag
from robid_link.kinds import MAX_RATE_HZ, MIN_RATE_HZ
from robid_link.safeopen import file_problem

__all__ = ["Log", "load_log", "file_sha256", "write_log_csv", "read_numeric_csv",
           "write_numeric_csv", "MAX_LOG_BYTES", "MAX_ARRAY_BYTES"]

#: a log file (an hour at 1 kHz of 7 joints as CSV is ~0.5 GB)
MAX_LOG_BYTES = 1 << 30
#: one array of an .npz or .mat log, as its header claims it
MAX_ARRAY_BYTES = 1 << 30

#: time steps longer than this many median steps split the log into segments
GAP_FACTOR = 2.5
#: relative jitter of the time step above which the log is resampled onto a uniform grid
JITTER_TOL = 0.01
#: time units a log's time column is often written in, by their size in seconds
_TIME_UNITS = (("milliseconds", 1e-3), ("microseconds", 1e-6), ("nanoseconds", 1e-9),
               ("minutes", 60.0))


@dataclass
class Log:
    """One log on the joint side: uniform time grid, arrays (samples × joints)."""

    path: str
    t: np.ndarray
    q: np.ndarray
    tau: np.ndarray
    qd: np.ndarray | None = None
    qdd: np.ndarray | None = None
    segments: list[slice] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: (n,) joints whose ``tau`` column holds a drive current (CSV ``i<j>``, npz ``current``)
    #: until ``identify.load_logs`` turns it into a torque
    current: np.ndarray | None = None
    #: raw currents (samples × n) of drives whose gain is to be identified (zero elsewhere;
    #: their share of ``tau`` is left out until then)
    currents: np.ndarray | None = None
    #: where the samples came from beyond the file (a bag's storage, topic, time range)
    source: dict[str, Any] = field(default_factory=dict)
    #: commanded positions at the same time stamps (a controller state's reference), if logged
    q_ref: np.ndarray | None = None
    #: (n,) joints whose torque the log holds (a controller's signal budget: positions of every
    #: axis, the torques of some); None: every joint's. A joint not held has NaN in ``tau``.
    tau_held: np.ndarray | None = None

    @property
    def held(self) -> np.ndarray:
        """(n,) bool: the joints whose torque this log holds."""
        if self.tau_held is None:
            return np.ones(self.q.shape[1], dtype=bool)
        return self.tau_held

    @property
    def partial(self) -> bool:
        """The log holds only some joints' torque."""
        return self.tau_held is not None and not bool(self.tau_held.all())

    @property
    def fs(self) -> float:
        return 1.0 / float(np.median(np.diff(self.t)))

    @property
    def n_joints(self) -> int:
        return int(self.q.shape[1])

    def __len__(self) -> int:
        return int(self.t.shape[0])


#: a file's digest by (path, inode, size, modification and change times): read once while
#: the file stays the same
_DIGESTS: dict[tuple[str, int, int, int, int], Future[str]] = {}
_DIGESTS_LOCK = threading.Lock()


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a log file; of a folder (a ROS 2 bag), over its files' names and bytes.
    A file's is read once per process while it stays the same (inode, size, times): a caller
    may ask ahead, on a thread (the CLI does, while the numerical modules load)."""
    p = Path(path)
    if p.is_dir():
        return _sha256(p)
    st = p.stat()
    key = (str(p.resolve()), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    with _DIGESTS_LOCK:
        done = _DIGESTS.get(key)
        if done is None:
            done = _DIGESTS[key] = Future()
            old = next((k for k, f in _DIGESTS.items() if f.done()), None)
            if len(_DIGESTS) > 64 and old is not None:  # the oldest finished one goes
                del _DIGESTS[old]
            mine = True
        else:
            mine = False
    if mine:
        try:
            done.set_result(_sha256(p))
        except BaseException as err:
            with _DIGESTS_LOCK:
                del _DIGESTS[key]
            done.set_exception(err)
    return done.result()


def _sha256(p: Path) -> str:
    h = hashlib.sha256()
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    for f in files:
        if p.is_dir():
            h.update(f.relative_to(p).as_posix().encode() + b"\0")
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def load_log(path: str | Path, n_joints: int, fs: float | None = None, *,
             joint_names: Sequence[str] | None = None, topic: str | None = None,
             effort_current: np.ndarray | None = None) -> Log:
    """Read and check a log; resample jittered time stamps, split at gaps. A ROS recording
    (:mod:`.bags`) needs the robot's ``joint_names`` (joints are matched by name); ``topic``
    picks its topic and ``effort_current`` marks joints whose effort is a drive current."""
    p = Path(path)
    problem = None if p.is_dir() else file_problem(p)
    if problem:
        raise DataError(f"{p}: log file {problem}")
    if is_bag(p):
        if joint_names is None or len(joint_names) != n_joints:
            raise DataError(f"{p}: a ROS recording needs the robot's joint names")
        return _load_bag(p, joint_names, topic, effort_current, fs)
    if p.is_dir():
        raise DataError(f"{p}: a folder, but not a ROS 2 bag (no metadata.yaml)")
    if topic is not None:
        raise DataError(f"{p}: --topic {topic} applies to ROS bags, this is not one")
    suffix = p.suffix.lower()
    if suffix == ".csv":
        cols = _read_csv(p)
    elif suffix == ".npz":
        cols = _read_npz(p)
    elif suffix == ".mat":
        cols = _read_mat(p, n_joints, fs)
    else:
        raise DataError(f"{p}: unknown log format '{suffix}' (expected .csv, .npz, .mat, a ROS "
                        "2 bag folder, .mcap or a ROS 1 .bag)")
    return _check_and_grid(p, cols, n_joints, fs)


def _load_bag(p: Path, names: Sequence[str], topic: str | None,
              effort_current: np.ndarray | None, fs: float | None) -> Log:
    bag = read_bag(p, names, topic)
    cols: dict[str, Any] = {"t": bag.t, "q": bag.q, "tau": bag.tau,
                            "__time__": "the messages' time stamps"}
    cols.update({k: v for k, v in (("qd", bag.qd), ("q_ref", bag.q_ref)) if v is not None})
    for note in bag.notes:
        warnings.warn(note, DataWarning, stacklevel=3)
    log = _check_and_grid(p, cols, len(names), fs)
    if effort_current is not None and np.any(effort_current):
        log.current = np.asarray(effort_current, dtype=bool)
    log.notes[:0] = bag.notes
    log.source = dict(bag.source, t_start_s=float(log.t[0]), t_end_s=float(log.t[-1]))
    return log


# ----------------------------------------------------------------------------- readers


def _read_csv(p: Path) -> dict[str, np.ndarray]:
    header, arr = read_numeric_csv(p, DataError, "a header t,q1..qn,tau1..taun")
    return {"__csv__": arr, "__header__": np.array(header, dtype=object)}


def _short(v: str, size: int = 30) -> str:
    return repr(v) if len(v) <= size else repr(v[: size - 3] + "...")


def read_numeric_csv(p: Path, error: type[RobidError], expected: str,
                     max_bytes: int = MAX_LOG_BYTES) -> tuple[list[str], np.ndarray]:
    """A CSV of numbers under a header: size-limited, every row as long as the header, every
    cell a number; errors are one line naming the file, line and column."""
    size = _size_checked(p, max_bytes, error)
    if size == 0:
        raise error(f"{p}: empty file, expected {expected}")
    rows: list[list[float]] = []
    try:
        with open(p, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if not header or not any(h.strip() for h in header):
                raise error(f"{p}: empty header, expected {expected}")
            header = [h.strip() for h in header]
            if len(set(header)) != len(header):
                dup = next(h for h in header if header.count(h) > 1)
                raise error(f"{p}: column {dup[:30]} appears twice")
            arr = _fast_rows(fh, len(header))
            if arr is not None:
                return header, arr
            fh.seek(0)
            reader = csv.reader(fh)
            next(reader)
            for row in reader:
                if not row:
                    continue
                if len(row) != len(header):
                    raise error(f"{p}: row {reader.line_num} has {len(row)} fields, header has "
                                f"{len(header)}")
                try:
                    rows.append([float(v) for v in row])
                except ValueError:
                    k = next(i for i, v in enumerate(row) if not _is_number(v))
                    raise error(f"{p}: row {reader.line_num}, column {header[k][:30]}: not a "
                                f"number: {_short(row[k])}") from None
    except UnicodeDecodeError as err:
        raise error(f"{p}: not a text CSV file (not UTF-8)") from err
    except csv.Error as err:
        raise error(f"{p}: malformed CSV at line {reader.line_num}: {err}") from err
    except OSError as err:
        raise error(f"{p}: cannot read: {err.strerror or err}") from err
    if not rows:
        raise error(f"{p}: no data rows")
    return header, np.array(rows, dtype=float)


def _fast_rows(fh: Any, width: int) -> np.ndarray | None:
    """The data rows by numpy's C reader (what the row-by-row reader below accepts, 20× as
    fast); None when it finds anything wrong, so that the slow reader names the line."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # "input contained no data"
            arr = np.loadtxt(_short_lines(fh), delimiter=",", comments=None, ndmin=2,
                             dtype=float, quotechar='"', encoding=None)
    except (ValueError, UserWarning):
        return None
    return arr if arr.shape[0] and arr.shape[1] == width else None


def _short_lines(fh: Any) -> Iterator[str]:
    """The lines of a file, stopping at one longer than the csv module's field limit (which
    the row-by-row reader then reports as malformed)."""
    limit = csv.field_size_limit()
    for line in fh:
        if len(line) > limit:
            raise ValueError("line over the csv field limit")
        yield line


def _is_number(v: str) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


def _size_checked(p: Path, max_bytes: int, error: type[RobidError] = DataError) -> int:
    try:
        size = p.stat().st_size
    except OSError as err:
        raise error(f"{p}: cannot read: {err.strerror or err}") from err
    if size > max_bytes:
        raise error(f"{p}: {size} bytes, more than the {max_bytes} allowed for a log")
    return size


def _npz_member_checked(p: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> None:
    """Read only the .npy header of a member: numeric dtype and a size within the limit."""
    name = info.filename
    with zf.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, _fortran, dtype = read_header(fh)
    if dtype.kind not in "iuf" or dtype.hasobject:
        raise DataError(f"{p}: array {_short(name)} has dtype {dtype}, expected numbers")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > MAX_ARRAY_BYTES:
        raise DataError(f"{p}: array {_short(name)} claims shape {shape} ({nbytes} bytes), more "
                        f"than the {MAX_ARRAY_BYTES} allowed")


def _read_npz(p: Path) -> dict[str, np.ndarray]:
    _size_checked(p, MAX_LOG_BYTES)
    try:
        with zipfile.ZipFile(p) as zf:
            infos = zf.infolist()
            if not infos:
                raise DataError(f"{p}: empty .npz file (no arrays)")
            if len(infos) > 64:
                raise DataError(f"{p}: {len(infos)} arrays, a log has at most 5")
            for info in infos:
                _npz_member_checked(p, zf, info)
        with np.load(p, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except DataError:
        raise
    except (OSError, ValueError, EOFError, KeyError, NotImplementedError, zipfile.BadZipFile,
            zlib.error) as err:
        raise DataError(f"{p}: not a readable .npz file ({_reason(err)})") from err


def _reason(err: BaseException) -> str:
    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    return f"{type(err).__name__}: {text[:80]}" if text else type(err).__name__


def _read_mat(p: Path, n: int, fs: float | None) -> dict[str, np.ndarray]:
    import scipy.io

    if fs is None or not math.isfinite(fs) or fs <= 0:
        raise DataError(f"{p}: a .mat log has no time stamps; give the sampling rate with --fs")
    if not MIN_RATE_HZ <= fs <= MAX_RATE_HZ:
        raise DataError(f"{p}: --fs {fs:g}: a robot's log runs at {MIN_RATE_HZ:g} Hz to "
                        f"{MAX_RATE_HZ:g} Hz (the rate in Hz, not the step in seconds?)")
    _size_checked(p, MAX_LOG_BYTES)
    try:
        for name, shape, _kind in scipy.io.whosmat(str(p)):
            if math.prod(shape) * 8 > MAX_ARRAY_BYTES:
                raise DataError(f"{p}: variable {_short(name)} claims shape {shape}, more than "
                                f"the {MAX_ARRAY_BYTES} bytes allowed")
        mat = scipy.io.loadmat(str(p))
    except DataError:
        raise
    except Exception as err:  # scipy's MATLAB reader fails in many ways on a damaged file
        raise DataError(f"{p}: not a readable MATLAB file ({_reason(err)})") from err
    arrays = {k: v for k, v in mat.items() if not k.startswith("__") and isinstance(v, np.ndarray)}
    mats = {k: v for k, v in arrays.items() if v.ndim == 2 and v.shape[0] > 1}
    if len(mats) != 1:
        raise DataError(f"{p}: expected one matrix (columns q, qd, qdd, tau), found {len(mats)}")
    (name, m), = mats.items()
    if m.dtype.kind not in "iuf":
        raise DataError(f"{p}: matrix {_short(name)} holds {m.dtype}, expected numbers")
    if m.shape[1] != 4 * n:
        raise DataError(f"{p}: matrix {_short(name)} has {m.shape[1]} columns, expected "
                        f"4×{n} = {4 * n} (q, qd, qdd, tau)")
    m = m.astype(float)
    t = np.arange(m.shape[0]) / fs
    return {"t": t, "q": m[:, :n], "qd": m[:, n:2 * n], "qdd": m[:, 2 * n:3 * n],
            "tau": m[:, 3 * n:]}


def _csv_columns(p: Path, cols: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    header = list(cols["__header__"])
    arr = cols["__csv__"]
    idx = {h: i for i, h in enumerate(header)}
    if "t" not in idx:
        raise DataError(f"{p}: column t missing")
    log_n = sum(1 for h in header if h.startswith("q") and h[1:].isdigit())
    if log_n and log_n != n:
        raise DataError(f"{p}: the log has {log_n} joints (q1..q{log_n}), the robot has {n}")
    out: dict[str, np.ndarray] = {"t": arr[:, idx["t"]]}
    for j in range(1, n + 1):
        if f"q{j}" not in idx:
            raise DataError(f"{p}: column q{j} missing")
    out["q"] = arr[:, [idx[f"q{j}"] for j in range(1, n + 1)]]
    torque_cols: list[str | None] = []
    for j in range(1, n + 1):
        given = [c for c in (f"tau{j}", f"i{j}") if c in idx]
        if len(given) == 2:
            raise DataError(f"{p}: columns tau{j} and i{j} both given; keep one per joint")
        torque_cols.append(given[0] if given else None)
    held = [c is not None for c in torque_cols]
    if not any(held):  # a partial log holds some joint's torque; this one none
        raise DataError(f"{p}: column tau1 missing (or i1: the drive's current)")
    out["tau"] = arr[:, [idx[c] for c in torque_cols if c is not None]]
    out["__current__"] = np.array([c is not None and c.startswith("i") for c in torque_cols])
    out["__held__"] = np.array(held)
    for key in ("qd", "qdd"):
        have = [f"{key}{j}" in idx for j in range(1, n + 1)]
        if any(have) and not all(have):
            missing = next(f"{key}{j}" for j in range(1, n + 1) if not have[j - 1])
            raise DataError(f"{p}: column {missing} missing (give all of {key}1..{key}{n} or none)")
        if all(have):
            out[key] = arr[:, [idx[f"{key}{j}"] for j in range(1, n + 1)]]
    known = {"t"} | {f"{k}{j}" for k in ("q", "qd", "qdd", "tau", "i")
                     for j in range(1, n + 1)}
    extra = [h for h in header if h not in known]
    if extra:
        raise DataError(f"{p}: unexpected column {extra[0][:30]} (expected t, q1..q{n}, "
                        f"tau1..tau{n} or currents i1..i{n}, optional qd1..qd{n}, "
                        f"qdd1..qdd{n})")
    return out


def _npz_torque_joints(p: Path, cols: dict[str, np.ndarray], n: int) -> np.ndarray | None:
    """A partial .npz log's ``torque_joints`` (joint numbers from 1, ascending: which joints'
    torques the columns of ``tau`` are) as a held mask; None when the array is absent."""
    if "torque_joints" not in cols:
        return None
    tj = np.asarray(cols["torque_joints"]).reshape(-1)
    if tj.dtype.kind not in "iu" or tj.size == 0 or np.any(np.diff(tj) <= 0) or \
            tj[0] < 1 or tj[-1] > n:
        raise DataError(f"{p}: array 'torque_joints' must list joint numbers 1..{n}, "
                        f"ascending, got {tj.tolist()[:8]}")
    held = np.zeros(n, dtype=bool)
    held[tj - 1] = True
    return held


_NPZ_KEYS = {"times": "t", "positions": "q", "velocities": "qd", "accelerations": "qdd",
             "torques": "tau"}


def _npz_columns(p: Path, cols: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    if "times" in cols or "positions" in cols:
        cols = {_NPZ_KEYS.get(k, k): v for k, v in cols.items()}
    current = "current" in cols
    if current and "tau" in cols:
        raise DataError(f"{p}: arrays 'tau' and 'current' both given; keep one")
    if current:
        cols = {("tau" if k == "current" else k): v for k, v in cols.items()}
    for key in ("t", "q", "tau"):
        if key not in cols:
            raise DataError(f"{p}: array '{key}' missing (expected t, q, tau or current "
                            "[, qd, qdd] or FloBaRoID's times, positions, torques)")
    for key, a in cols.items():
        if key in ("t", "q", "qd", "qdd", "tau") and np.asarray(a).dtype.kind not in "iuf":
            raise DataError(f"{p}: array '{key}' holds {np.asarray(a).dtype}, expected numbers")
    out = {"t": np.asarray(cols["t"], dtype=float).reshape(-1)}
    held = _npz_torque_joints(p, cols, n)
    for key in ("q", "qd", "qdd", "tau", "q_ref"):
        if key not in cols:
            continue
        a = np.asarray(cols[key], dtype=float)
        if a.ndim != 2:
            raise DataError(f"{p}: array '{key}' must be samples × joints, got shape {a.shape}")
        width = n if key != "tau" or held is None else int(held.sum())
        if a.shape[1] != width:
            what = "the robot has" if width == n else "torque_joints names"
            raise DataError(f"{p}: array '{key}' has {a.shape[1]} joints, {what} {width}")
        out[key] = a
    if held is not None:
        out["__held__"] = held
    if current:
        out["__current__"] = np.ones(n, dtype=bool)
    return out


# ----------------------------------------------------------------------------- checks


def _time_units(p: Path, where: str, step: float) -> None:
    """Refuse time stamps whose rate no robot's log has, with the unit they look like."""
    rate = 1.0 / step
    if MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
        return
    hint = next((f": read as {unit} it is {rate / size:.4g} Hz — give the time in seconds"
                 for unit, size in _TIME_UNITS
                 if MIN_RATE_HZ <= rate / size <= MAX_RATE_HZ), ": is it in seconds?")
    raise DataError(f"{p}: {where}: a time step of {step:.4g} per sample is a rate of "
                    f"{rate:.3g} Hz, outside the {MIN_RATE_HZ:g} Hz to {MAX_RATE_HZ:g} Hz a "
                    f"robot's log runs at{hint}")


def _check_and_grid(p: Path, cols: dict[str, np.ndarray], n: int, fs: float | None) -> Log:
    time_col = str(cols.pop("__time__", "column t" if "__csv__" in cols else
                            "array 'times'" if "times" in cols else "array 't'"))
    cols = _csv_columns(p, cols, n) if "__csv__" in cols else _npz_columns(p, cols, n)
    current = cols.pop("__current__", None)
    held = cols.pop("__held__", None)
    t = cols["t"]
    nsamp = t.shape[0]
    for key, a in cols.items():
        if a.shape[0] != nsamp:
            raise DataError(f"{p}: '{key}' has {a.shape[0]} samples, t has {nsamp}")
        if np.isfinite(a).all():
            continue
        bad = ~np.isfinite(a)
        if bad.any():
            row = int(np.argwhere(bad)[0][0])
            col = key if a.ndim == 1 else f"{key}{int(np.argwhere(bad)[0][1]) + 1}"
            kind = "NaN" if np.isnan(a[bad]).any() else "inf"
            raise DataError(f"{p}: column {col} has {kind} at sample {row + 1}")
    if nsamp < 10:
        raise DataError(f"{p}: only {nsamp} samples")
    dt = np.diff(t)
    if not np.all(np.isfinite(dt)):
        raise DataError(f"{p}: time stamps span more than a float can hold")
    if np.any(dt == 0):
        i = int(np.argmax(dt == 0))
        raise DataError(f"{p}: duplicate time stamp {t[i]:.6g} s at samples {i + 1} and {i + 2}")
    if np.any(dt < 0):
        i = int(np.argmax(dt < 0))
        raise DataError(f"{p}: time goes backwards at sample {i + 2} "
                        f"({t[i]:.6g} → {t[i + 1]:.6g} s)")
    notes: list[str] = []
    h = float(np.median(dt))
    _time_units(p, time_col, h)
    gaps = np.flatnonzero(dt > GAP_FACTOR * h)
    bounds = [0, *(gaps + 1).tolist(), nsamp]
    pieces = [(bounds[i], bounds[i + 1]) for i in range(len(bounds) - 1)]
    if len(gaps):
        notes.append(f"{p.name}: {len(gaps)} gap(s) in the time stamps (longest "
                     f"{dt[gaps].max():.3g} s); the log is split into {len(pieces)} segments")
        warnings.warn(notes[-1], DataWarning, stacklevel=3)
    jitter = float(np.max(np.abs(dt[dt <= GAP_FACTOR * h] - h)) / h)
    keys = [k for k in ("q", "qd", "qdd", "tau", "q_ref") if k in cols]
    if held is not None and not held.all():  # joints not logged: NaN, never a number
        tau = np.full((nsamp, n), np.nan)
        tau[:, held] = cols["tau"]
        cols["tau"] = tau
    else:
        held = None
    if jitter > JITTER_TOL:
        notes.append(f"{p.name}: time step varies by up to {100 * jitter:.0f} % around "
                     f"{1e3 * h:.3g} ms; resampled onto a uniform grid")
        warnings.warn(notes[-1], DataWarning, stacklevel=3)
        out: dict[str, list[np.ndarray]] = {k: [] for k in ["t", *keys]}
        segs: list[slice] = []
        start = 0
        for a, b in pieces:
            tt = t[a:b]
            grid = tt[0] + h * np.arange(int(np.floor((tt[-1] - tt[0]) / h + 1e-9)) + 1)
            out["t"].append(grid)
            for k in keys:
                out[k].append(_interp(grid, tt, cols[k][a:b], cubic=k in ("q", "q_ref")))
            segs.append(slice(start, start + grid.size))
            start += grid.size
        arrays = {k: np.concatenate(v) for k, v in out.items()}
    else:
        arrays = {"t": t, **{k: cols[k] for k in keys}}
        segs = [slice(a, b) for a, b in pieces]
    return Log(path=str(p), t=arrays["t"], q=arrays["q"], tau=arrays["tau"],
               qd=arrays.get("qd"), qdd=arrays.get("qdd"), segments=segs, notes=notes,
               current=current if current is not None and current.any() else None,
               q_ref=arrays.get("q_ref"), tau_held=held)


def _interp(grid: np.ndarray, t: np.ndarray, y: np.ndarray, cubic: bool) -> np.ndarray:
    if cubic and t.size >= 4:
        from scipy.interpolate import CubicSpline

        return np.asarray(CubicSpline(t, y, axis=0)(grid))
    return np.stack([np.interp(grid, t, y[:, j]) for j in range(y.shape[1])], axis=1)


def write_log_csv(path: str | Path, t: np.ndarray, q: np.ndarray, tau: np.ndarray,
                  qd: np.ndarray | None = None, qdd: np.ndarray | None = None, *,
                  current: bool = False, torque_joints: Sequence[int] | None = None) -> None:
    """Write a log in the CSV layout of DESIGN.md (t, q…, [qd…, qdd…,] tau…); with
    ``current`` the last columns are drive currents i1..in; ``torque_joints`` (from 1): only
    those joints' torques (a partial log)."""
    n = q.shape[1]
    keep = list(range(1, n + 1)) if torque_joints is None else sorted(torque_joints)
    names = ["t"] + [f"q{j}" for j in range(1, n + 1)]
    blocks = [t[:, None], q]
    for key, a in (("qd", qd), ("qdd", qdd)):
        if a is not None:
            names += [f"{key}{j}" for j in range(1, n + 1)]
            blocks.append(a)
    names += [f"{'i' if current else 'tau'}{j}" for j in keep]
    blocks.append(tau[:, [j - 1 for j in keep]])
    write_numeric_csv(path, names, np.hstack(blocks))


def write_numeric_csv(path: str | Path, names: Sequence[str], rows: np.ndarray,
                      fmt: str = "%.10g", chunk: int = 20_000) -> None:
    """A header line and the rows, as ``np.savetxt(..., delimiter=",", fmt=fmt)`` writes
    them (the same bytes), formatted a block of rows at a time: twice as fast."""
    line = ",".join([fmt] * rows.shape[1]) + "\n"
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(",".join(names) + "\n")
        for a in range(0, rows.shape[0], chunk):
            block = rows[a: a + chunk]
            fh.write((line * block.shape[0]) % tuple(block.ravel().tolist()))
