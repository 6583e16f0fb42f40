"""Arrays for the HTML report: compact, deflated, base64 text the page inflates with the
browser's own ``DecompressionStream`` (report.js ``unpack``).

Two encodings. ``f8``: float64 exactly, byte-shuffled (each byte of the numbers in a plane
of its own, as HDF5's shuffle filter) — for time stamps. ``q``: a signal stored to 2⁻²⁰ of
its range (a millionth of the plot's full height: far below any sensor's resolution and any
pixel), as int32 first differences, byte-shuffled: a torque at 1 kHz takes about 1.9 bytes a
sample instead of 4, a smooth model torque 0.2. NaN rows (gaps) are kept as ranges.
"""

from __future__ import annotations

import base64
import zlib
from typing import Any

import numpy as np

__all__ = ["pack", "unpack", "BITS"]

#: a signal's range is split into 2**BITS steps
BITS = 20


def _deflate(a: np.ndarray) -> str:
    planes = a.view(np.uint8).reshape(-1, a.itemsize).T.tobytes()
    return base64.b64encode(zlib.compress(planes, 6)).decode("ascii")


def _inflate(text: str, dtype: str, n: int) -> np.ndarray:
    size = np.dtype(dtype).itemsize
    planes = np.frombuffer(zlib.decompress(base64.b64decode(text)), np.uint8)
    return planes.reshape(size, n).T.copy().view(dtype).ravel()


def _nan_runs(bad: np.ndarray) -> list[list[int]]:
    edges = np.diff(np.concatenate(([0], bad.astype(np.int8), [0])))
    return [[int(a), int(b)] for a, b in zip(np.flatnonzero(edges == 1),
                                             np.flatnonzero(edges == -1), strict=True)]


def pack(values: Any, dtype: str = "q") -> dict[str, Any]:
    """``values`` (1-D) as ``{"dtype": "f8", "n", "z"}`` (exact) or ``{"dtype": "q", "n",
    "lo", "step", "nan", "z"}`` (to 2⁻²⁰ of the range)."""
    a = np.asarray(values, dtype=float).ravel()
    if dtype == "f8":
        return {"dtype": "f8", "n": int(a.size), "z": _deflate(np.ascontiguousarray(a, "<f8"))}
    if dtype != "q":
        raise ValueError(f"pack: dtype {dtype!r} (choose f8 or q)")
    bad = ~np.isfinite(a)
    good = a[~bad]
    lo = float(good.min()) if good.size else 0.0
    span = float(good.max()) - lo if good.size else 0.0
    step = span / 2**BITS if span > 0 else 1.0
    steps = np.zeros(a.size, np.int64)
    steps[~bad] = np.round((good - lo) / step)
    deltas = np.diff(steps, prepend=0).astype("<i4")
    return {"dtype": "q", "n": int(a.size), "lo": lo, "step": step,
            "nan": _nan_runs(bad), "z": _deflate(deltas)}


def unpack(doc: dict[str, Any]) -> np.ndarray:
    """The array ``pack`` wrote (as the page decodes it)."""
    n = int(doc["n"])
    if doc["dtype"] == "f8":
        return _inflate(doc["z"], "<f8", n)
    out = doc["lo"] + doc["step"] * np.cumsum(_inflate(doc["z"], "<i4", n), dtype=np.int64)
    for a, b in doc["nan"]:
        out[a:b] = np.nan
    return out
