"""The report's signals: per data file and joint, measured, model and CAD torque, position,
velocity and the filtered residual at the full rate; per joint the residual's statistics
(histogram, autocorrelation, cross-correlation with the joint velocity)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.ident.data.preprocess import Piece, Prepared, ZeroPhaseFilter
from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.regressor import rigid_regressor
from robid_link.ident.report.pack import pack

__all__ = ["signals", "joint_units", "white_step", "MAX_SAMPLES", "LAGS"]

#: samples per file embedded as they are; a longer file keeps each bucket's min and max
MAX_SAMPLES = 200_000
#: lags of the residual's auto- and cross-correlation (as MATLAB's resid)
LAGS = 25
#: two-sided 99 % quantile of the normal distribution: the whiteness band is ±Z99/√N
Z99 = 2.5758
HIST_BINS = 41


def joint_units(joint_type: str) -> dict[str, str]:
    """Units of a joint's position, velocity and effort."""
    if joint_type == "prismatic":
        return {"q": "m", "qd": "m/s", "qdd": "m/s²", "tau": "N"}
    return {"q": "rad", "qd": "rad/s", "qdd": "rad/s²", "tau": "N·m"}


def _filtered_rows(prep: Prepared) -> np.ndarray:
    """Rows whose states were filtered (segments too short for the filter hold no states)."""
    ok = np.zeros(len(prep.log), bool)
    for seg in prep.log.segments:
        if seg.stop - seg.start >= 3 * prep.filt.settle:
            ok[seg] = True
    return ok


def _model_torques(res: IdentResult, prep: Prepared, ok: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """(model, CAD or None, filtered residual) on every row, NaN where nothing was filtered."""
    assert res.problem is not None
    robot = res.problem.robot
    nan = np.full(prep.log.tau.shape, np.nan)
    model, resid_f = nan.copy(), nan.copy()
    model[ok] = res.predict(prep)[ok]
    cad = None
    if robot.nominal is not None:
        cad = nan.copy()
        cad[ok] = rigid_regressor(robot, prep.q[ok], prep.qd[ok], prep.qdd[ok]) @ robot.nominal
        if prep.tau_known is not None:
            cad[ok] += prep.tau_known[ok]
    resid = prep.tau_measured - model
    for seg in prep.log.segments:
        if ok[seg.start]:
            resid_f[seg] = prep.filt.apply(resid[seg])
    return model, cad, resid_f


def _envelope(a: np.ndarray, k: int) -> np.ndarray:
    """Min and max of each bucket of k rows, interleaved (2·⌈N/k⌉ rows): the extremes kept."""
    n = a.shape[0]
    pad = (-n) % k
    b = np.concatenate([a, np.full((pad, *a.shape[1:]), np.nan)]).reshape(-1, k, *a.shape[1:])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN bucket (a gap) is NaN
        lo, hi = np.nanmin(b, axis=1), np.nanmax(b, axis=1)
    return np.stack([lo, hi], axis=1).reshape(-1, *a.shape[1:])


def _ranges(pieces: Sequence[Piece], prep: Prepared) -> list[list[float]]:
    t = prep.log.t
    return [[float(t[pc.lo]), float(t[pc.hi - 1])] for pc in pieces if pc.prep is prep]


def signals(res: IdentResult) -> tuple[list[dict[str, Any]], list[dict[str, Any]],
                                        dict[str, Any] | None]:
    """(files, series, residual statistics) of a fitted result: per data and validation file
    its facts (role, samples, rate, the time ranges that trained and validated) and its packed
    signals per joint; the statistics of ``residual_stats``. Nothing for a result that keeps
    no fitted problem."""
    pb = res.problem
    if pb is None or res.theta is None or res.design is None:
        return [], [], None
    files, series = [], []
    resid: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    roles = [("data", p) for p in pb.preps] + [("validate", p) for p in pb.vpreps]
    sha = {f["path"]: f.get("sha256") for f in res.data_files}
    for role, prep in roles:
        log = prep.log
        ok = _filtered_rows(prep)
        model, cad, resid_f = _model_torques(res, prep, ok)
        resid[id(prep)] = (prep.tau_measured - model, resid_f)
        n = len(log)
        k = max(1, math.ceil(n / MAX_SAMPLES))
        files.append({"name": Path(log.path).name, "path": str(log.path), "role": role,
                      "sha256": sha.get(log.path), "samples": n, "rate_hz": float(log.fs),
                      "duration_s": float(log.t[-1] - log.t[0]), "bucket": k,
                      "train": _ranges(pb.train, prep), "valid": _ranges(pb.valid, prep)})
        t = log.t - log.t[0]
        modelled = np.zeros(n, bool)  # rows that trained or validated (no filter edges)
        for pc in (*pb.train, *pb.valid):
            if pc.prep is prep:
                modelled[pc.lo: pc.hi] = True
        sig = {"meas": prep.tau_measured, "model": model, "cad": cad,
               "q": np.where(ok[:, None], prep.q, np.nan),
               "qd": np.where(ok[:, None], prep.qd, np.nan),
               "rf": np.where(modelled[:, None], resid_f, np.nan)}
        if k > 1:  # each pair: a bucket's min and max, placed at its start and middle
            t = np.stack([t[::k], t[::k] + 0.5 * k / log.fs], axis=1).ravel()
            sig = {key: None if a is None else _envelope(a, k) for key, a in sig.items()}
        series.append({"file": len(files) - 1, "t0": float(log.t[0]), "t": pack(t, "f8"),
                       "joints": [{key: None if a is None else pack(a[:, j])
                                   for key, a in sig.items()} for j in range(log.tau.shape[1])]})
    return files, series, residual_stats(res, resid)


def _xcorr(a: Sequence[np.ndarray], b: Sequence[np.ndarray], lags: int) -> np.ndarray:
    """Σ a(i+k)·b(i) over the pieces for k = −lags…lags, each piece on its own."""
    out = np.zeros(2 * lags + 1)
    for x, y in zip(a, b, strict=True):
        m = x.size
        for i, k in enumerate(range(-lags, lags + 1)):
            if abs(k) < m:
                out[i] += float(x[max(k, 0): m + min(k, 0)] @ y[max(-k, 0): m - max(k, 0)])
    return out


def white_step(filt: ZeroPhaseFilter) -> int:
    """Rows between samples of filtered white noise that are uncorrelated: the first zero of
    the filter's own noise autocorrelation (about 0.55/fc for the 4th-order zero-phase
    Butterworth). A residual sampled so is white when the model is adequate."""
    if not filt.active:
        return 1
    n = 8 * filt.settle + 1
    impulse = np.zeros(n)
    impulse[n // 2] = 1.0
    h = filt.apply(impulse)
    r = np.correlate(h, h, "full")[n - 1:]
    return max(1, int(np.argmax(r <= 0)))


def residual_stats(res: IdentResult, resid: dict[int, tuple[np.ndarray, np.ndarray]]
                   ) -> dict[str, Any]:
    """Per joint: the raw residual's histogram (with mean and σ for the normal overlay), the
    filtered residual's autocorrelation and its cross-correlation with the joint velocity over
    ±LAGS lags, sampled where filtered white noise is white (``white_step``), with the 99 %
    band for white noise; on the held-out rows (else the training rows). ``resid``: per prepared log
    (by id) its raw and filtered residual on every row."""
    pb = res.problem
    assert pb is not None
    pieces = pb.valid or pb.train
    filt = pb.preps[0].filt
    step = white_step(filt)
    raw: list[np.ndarray] = []
    smooth: list[np.ndarray] = []
    vel: list[np.ndarray] = []
    held: list[np.ndarray] = []  # a partial log's piece counts for the joints it holds
    for pc in pieces:
        prep = pc.prep
        r, rf = resid[id(prep)]
        raw.append(r[pc.lo: pc.hi])
        smooth.append(rf[pc.lo: pc.hi: step])
        vel.append(prep.qd[pc.lo: pc.hi: step])
        held.append(prep.log.held)
    n_dec = sum(x.shape[0] for x in smooth)
    joints: list[dict[str, Any]] = []
    for j in range(pb.robot.n):
        mine = [k for k, h in enumerate(held) if h[j]]
        if not mine:  # partial logs: none of these rows holds the joint's torque
            joints.append({"joint": j + 1, "mean": None, "std": None, "n": 0, "outside": 0,
                           "hist": {"edges": [], "counts": []}, "acf": [], "ccf": []})
            continue
        rj = np.concatenate([raw[k][:, j] for k in mine])
        mean, std = float(rj.mean()), float(rj.std())
        half = 4.0 * std if std > 0 else 1.0
        counts, edges = np.histogram(rj, bins=HIST_BINS, range=(mean - half, mean + half))
        sj = [smooth[k][:, j] for k in mine]
        vj = [vel[k][:, j] for k in mine]
        e = [x - np.concatenate(sj).mean() for x in sj]
        u = [x - np.concatenate(vj).mean() for x in vj]
        ee, uu = sum(float(x @ x) for x in e), sum(float(x @ x) for x in u)
        acf = _xcorr(e, e, LAGS) / ee if ee > 0 else np.zeros(2 * LAGS + 1)
        ccf = _xcorr(e, u, LAGS) / math.sqrt(ee * uu) if ee > 0 and uu > 0 else \
            np.zeros(2 * LAGS + 1)
        joints.append({"joint": j + 1, "mean": mean, "std": std, "n": int(rj.size),
                       "outside": int(rj.size - counts.sum()),
                       "hist": {"edges": edges.tolist(), "counts": counts.tolist()},
                       "acf": acf.tolist(), "ccf": ccf.tolist()})
    return {"rows": "held-out" if pb.valid else "training", "lag_s": step / filt.fs,
            "cutoff_hz": filt.cutoff_hz, "n_lagged": n_dec, "band": Z99 / math.sqrt(max(n_dec, 1)),
            "lags": LAGS, "joints": joints}
