"""Log formats and every bad input's one-line message."""

from __future__ import annotations

import hashlib
import os

import numpy as np
import pytest
import scipy.io

from robid_link.exceptions import DataError, DataWarning
from robid_link.ident.data.logs import file_sha256, load_log, write_log_csv


def _log(n=3, samples=200, fs=100.0):
    t = np.arange(samples) / fs
    q = np.sin(np.outer(t, np.arange(1, n + 1)))
    tau = np.cos(np.outer(t, np.arange(1, n + 1)))
    return t, q, tau


def _csv(tmp_path, header, rows, name="log.csv"):
    p = tmp_path / name
    p.write_text(",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    return p


def test_csv_roundtrip_with_derivatives(tmp_path):
    t, q, tau = _log()
    p = tmp_path / "ok.csv"
    write_log_csv(p, t, q, tau, qd=q * 2, qdd=q * 3)
    log = load_log(p, 3)
    np.testing.assert_allclose(log.q, q)
    np.testing.assert_allclose(log.qd, 2 * q)
    np.testing.assert_allclose(log.tau, tau)
    assert log.segments == [slice(0, 200)]
    assert log.fs == pytest.approx(100.0)


def test_npz_ours_and_flobaroid_keys(tmp_path):
    t, q, tau = _log()
    np.savez(tmp_path / "a.npz", t=t, q=q, tau=tau)
    np.savez(tmp_path / "b.npz", times=t, positions=q, velocities=q, torques=tau)
    a, b = load_log(tmp_path / "a.npz", 3), load_log(tmp_path / "b.npz", 3)
    np.testing.assert_allclose(a.tau, b.tau)
    assert a.qd is None and b.qd is not None


def test_fduroid_mat_needs_fs(tmp_path):
    t, q, tau = _log()
    scipy.io.savemat(tmp_path / "f.mat", {"data": np.hstack([q, q, q, tau])})
    log = load_log(tmp_path / "f.mat", 3, fs=100.0)
    np.testing.assert_allclose(log.tau, tau)
    assert log.t[1] == pytest.approx(0.01)
    with pytest.raises(DataError, match=r"f\.mat: a \.mat log has no time stamps; give .* --fs"):
        load_log(tmp_path / "f.mat", 3)
    with pytest.raises(DataError, match="has 12 columns, expected 4×2 = 8"):
        load_log(tmp_path / "f.mat", 2, fs=100.0)


def test_jittered_stamps_are_resampled(tmp_path):
    t, _, tau = _log(samples=400)
    t = t + np.random.default_rng(0).uniform(-0.002, 0.002, t.size)
    q = np.sin(np.outer(t, [1, 2, 3]))
    p = tmp_path / "jit.csv"
    write_log_csv(p, t, q, tau)
    with pytest.warns(DataWarning, match="resampled onto a uniform grid"):
        log = load_log(p, 3)
    assert np.ptp(np.diff(log.t)) < 1e-9
    assert np.abs(log.q - np.sin(np.outer(log.t, [1, 2, 3]))).max() < 1e-5


def test_gaps_split_the_log(tmp_path):
    t, q, tau = _log(samples=400)
    t[200:] += 1.0
    p = tmp_path / "gap.csv"
    write_log_csv(p, t, q, tau)
    with pytest.warns(DataWarning, match="1 gap"):
        log = load_log(p, 3)
    assert log.segments == [slice(0, 200), slice(200, 400)]


BAD_CSV = [
    # a log without tau3 is a partial log (test_partial_logs.py); without any torque: refused
    (["t", "q1", "q2", "q3"], "column tau1 missing"),
    (["q1", "q2", "q3", "tau1", "tau2", "tau3"], "column t missing"),
    (["t", "q1", "q2", "q3", "q4", "tau1", "tau2", "tau3", "tau4"],
     "the log has 4 joints (q1..q4), the robot has 3"),
    (["t", "q1", "q2", "q3", "tau1", "tau2", "tau3", "temp"], "unexpected column temp"),
    (["t", "q1", "q2", "q3", "qd1", "tau1", "tau2", "tau3"], "column qd2 missing"),
]


@pytest.mark.parametrize(("header", "message"), BAD_CSV)
def test_bad_csv_columns(tmp_path, header, message):
    rows = [[0.01 * k] * len(header) for k in range(20)]
    p = _csv(tmp_path, header, rows)
    with pytest.raises(DataError) as err:
        load_log(p, 3)
    assert str(err.value).startswith(f"{p}: {message}")
    assert "\n" not in str(err.value)


HEADER = ["t", "q1", "q2", "q3", "tau1", "tau2", "tau3"]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: r[5].__setitem__(4, "nan"), "column tau1 has NaN at sample 6"),
        (lambda r: r[7].__setitem__(2, "inf"), "column q2 has inf at sample 8"),
        (lambda r: r[3].__setitem__(0, r[2][0]), "duplicate time stamp"),
        (lambda r: r[4].__setitem__(0, 0.0), "time goes backwards at sample 5"),
        (lambda r: r[2].__setitem__(3, "abc"), "row 4, column q3: not a number: 'abc'"),
        (lambda r: r[2].pop(), "row 4 has 6 fields, header has 7"),
    ],
)
def test_bad_csv_values(tmp_path, edit, message):
    rows = [[0.01 * k, 0.1, 0.2, 0.3, 1.0, 2.0, 3.0] for k in range(20)]
    edit(rows)
    p = _csv(tmp_path, HEADER, rows)
    with pytest.raises(DataError, match=message.replace("(", r"\(").replace(")", r"\)")) as err:
        load_log(p, 3)
    assert str(err.value).startswith(str(p)) and "\n" not in str(err.value)


def test_bad_files(tmp_path):
    with pytest.raises(DataError, match="log file not found"):
        load_log(tmp_path / "missing.csv", 3)
    (tmp_path / "x.parquet").write_text("x")
    with pytest.raises(DataError, match=r"unknown log format '\.parquet'"):
        load_log(tmp_path / "x.parquet", 3)
    (tmp_path / "e.csv").write_text("")
    with pytest.raises(DataError, match="empty file"):
        load_log(tmp_path / "e.csv", 3)
    (tmp_path / "h.csv").write_text(",".join(HEADER) + "\n")
    with pytest.raises(DataError, match="no data rows"):
        load_log(tmp_path / "h.csv", 3)
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00\x81garbage")
    with pytest.raises(DataError, match="not a text CSV file"):
        load_log(tmp_path / "bin.csv", 3)
    (tmp_path / "bad.npz").write_text("not a zip")
    with pytest.raises(DataError, match="not a readable .npz file"):
        load_log(tmp_path / "bad.npz", 3)
    t, q, tau = _log()
    np.savez(tmp_path / "nokey.npz", t=t, q=q)
    with pytest.raises(DataError, match="array 'tau' missing"):
        load_log(tmp_path / "nokey.npz", 3)
    np.savez(tmp_path / "wrongn.npz", t=t, q=q, tau=tau)
    with pytest.raises(DataError, match="array 'q' has 3 joints, the robot has 7"):
        load_log(tmp_path / "wrongn.npz", 7)
    np.savez(tmp_path / "short.npz", t=t[:5], q=q[:5], tau=tau[:5])
    with pytest.raises(DataError, match="only 5 samples"):
        load_log(tmp_path / "short.npz", 3)
    np.savez(tmp_path / "len.npz", t=t, q=q[:-1], tau=tau)
    with pytest.raises(DataError, match="'q' has 199 samples, t has 200"):
        load_log(tmp_path / "len.npz", 3)


def test_a_files_digest_is_read_once_and_again_when_the_file_changes(tmp_path, monkeypatch):
    """The digest the result records: asked twice (ahead by the CLI, then by identify), the
    file is read once; a file rewritten in place (same size) gets its new digest."""
    from robid_link.ident.data import logs

    reads = []
    monkeypatch.setattr(logs, "_sha256", lambda p, read=logs._sha256: reads.append(p) or read(p))
    log = tmp_path / "log.csv"
    log.write_bytes(b"t,q1,tau1\n0,0,0\n")
    first = file_sha256(log)
    assert first == hashlib.sha256(log.read_bytes()).hexdigest()
    assert file_sha256(str(log)) == first and len(reads) == 1
    log.write_bytes(b"t,q1,tau1\n0,0,1\n")
    st = log.stat()  # a coarse clock could give the rewrite the same time: move it on
    os.utime(log, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert file_sha256(log) == hashlib.sha256(log.read_bytes()).hexdigest() != first
    with pytest.raises(FileNotFoundError):
        file_sha256(tmp_path / "missing.csv")
