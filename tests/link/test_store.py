"""The store: one daemon per state dir, raw logs content-hashed and durable before their row,
journal and run states, read-only access for operator commands (each on both backends: a
cell's SQLite and a plant's real PostgreSQL); the daemon config's errors."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import yaml

from robid_link.config import load_daemon_config
from robid_link.exceptions import ConfigError, RobidError, StoreLockedError
from robid_link.jobs import MotionProgram
from robid_link.link.store import Store

from .conftest import QUICK, Backend, write_config


def test_two_daemons_never_share_a_state_dir(tmp_path: Path) -> None:
    with Store(tmp_path / "s"):
        with pytest.raises(StoreLockedError, match=r"is in use by another daemon \(pid \d+\)"):
            Store(tmp_path / "s")
    Store(tmp_path / "s").close()  # released on close


def test_logs_are_content_hashed_and_idempotent(tmp_path: Path, backend: Backend) -> None:
    with backend.store(tmp_path / "s") as st:
        data = b"t,q1,tau1\n0,0,0\n"
        sha = st.put_log(data)
        assert sha == hashlib.sha256(data).hexdigest()
        assert st.put_log(data) == sha and st.log_count() == 1
        assert st.check_log(sha).read_bytes() == data
        path = st.log_path(sha)
        path.chmod(0o644)
        path.write_bytes(b"damaged")
        with pytest.raises(RobidError, match="stored log damaged"):
            st.check_log(sha)


def test_runs_experiments_and_journal(tmp_path: Path, backend: Backend) -> None:
    with backend.store(tmp_path / "s") as st:
        run = st.create_run("quick", "operator", {}, [("a", "rigid_body"), ("b", "friction")])
        st.set_run(run, "running", step="experiment 1/2 a")
        st.step(run, "a", "giving", attempt=1, nonce="n1", program_sha="p")
        st.step(run, "a", "stored", log_sha="abc")
        rec = st.run(run)
        assert rec["state"] == "running" and rec["progress"] == {"stored": 1, "total": 2}
        assert [j["step"] for j in st.journal(run)] == ["queued", "running", "giving", "stored"]
        assert st.unfinished_runs() == [run]
        st.set_run(run, "failed", error="boom")
        assert st.run(run)["error"] == "boom" and st.unfinished_runs() == []
        with pytest.raises(ConfigError, match="run nope: not in the store"):
            st.run("nope")
    with backend.reader(tmp_path / "s") as ro:  # while no daemon holds it
        assert ro.runs()[0]["run_id"] == run


def test_programs_and_approvals(tmp_path: Path, backend: Backend) -> None:
    prog = MotionProgram("rb", {"traj.csv": b"t,q1\n0,0\n", "mod": b"MODULE x\nENDMODULE\n"},
                         1.0, {"kind": "rigid_body"})
    with backend.store(tmp_path / "s") as st:
        sha = st.put_program("key1", prog)
        assert st.program_for("key1") == sha == prog.sha256
        assert st.load_program(sha) == prog
        assert not st.approved(sha)
        st.approve(sha, "quick", "rb", "tester")
        assert st.approved(sha)
        (st.dir / "programs" / sha / "mod").write_bytes(b"MODULE evil\n")
        with pytest.raises(RobidError, match="stored program damaged"):
            st.load_program(sha)


def test_readonly_store_needs_one(tmp_path: Path, backend: Backend) -> None:
    with pytest.raises(ConfigError, match="holds no store yet"):
        backend.reader(tmp_path / "none")


@pytest.mark.parametrize("readonly", [True, False])
def test_a_damaged_sqlite_file_is_one_line(tmp_path: Path, readonly: bool) -> None:
    """Junk in robid.sqlite: the reader and the daemon say which state dir, not a traceback."""
    (tmp_path / "robid.sqlite").write_bytes(b"\x00junk" * 300)
    with pytest.raises(RobidError, match=rf"^state_dir: {tmp_path}: cannot (read its store|"
                                         r"connect) \(file is not a database\)$"):
        Store(tmp_path, readonly=readonly).close()


@pytest.mark.parametrize("change, message", [
    ({"robot": None}, "missing key 'robot'"),
    ({"colour": 1}, r"unknown key 'colour' \(known: campaigns, control_socket, driver, "),
    ({"driver": {"share": "x"}}, "driver: missing key 'name'"),
    ({"driver": ["file_share"]}, "driver: expected a mapping, got list"),
    ({"campaigns": {"q": {**QUICK, "colour": 1}}},
     r"campaigns\.q: unknown key 'colour' \(known: add, backoff_s, "),
    ({"campaigns": {"q": {"retries": 1}}}, r"campaigns\.q: missing key 'experiments'"),
    ({"campaigns": {"q": ["rigid_body"]}}, r"campaigns\.q: expected a mapping, got list"),
    ({"socket_mode": "rw"}, "socket_mode: expected octal"),
    ({"campaigns": {}}, "campaigns: expected a mapping"),
    ({"campaigns": {"a b": QUICK}}, "campaigns.a b: names are"),
    ({"campaigns": {"q": {"experiments": []}}}, r"campaigns\.q\.experiments: expected a "
                                                "non-empty list"),
    ({"campaigns": {"q": {**QUICK, "retries": -1}}}, r"campaigns\.q\.retries: expected a "
                                                     "non-negative integer"),
    ({"campaigns": {"q": {**QUICK, "method": "magic"}}}, r"campaigns\.q\.method"),
    ({"campaigns": {"q": {"experiments": [{"kind": "dance"}]}}},
     r"campaigns\.q\.experiments\[0\]\.kind: expected one of"),
    ({"campaigns": {"q": {"experiments": ["rigid_body", {"kind": "rigid_body",
                                                          "id": "rigid_body"}]}}},
     r"experiments\[1\]\.id: 'rigid_body' is used twice"),
    ({"campaigns": {"q": {"experiments": [{"kind": "friction", "id": "../x"}]}}},
     r"experiments\[0\]\.id: .*expected 1-64 letters"),
    ({"campaigns": {"q": {**QUICK, "reduced_speed_first": 2}}},
     r"reduced_speed_first: expected a fraction"),
])
def test_bad_config_names_the_key(tmp_path: Path, change: dict, message: str) -> None:
    path = write_config(tmp_path)
    doc = yaml.safe_load(path.read_text())
    for k, v in change.items():
        if v is None:
            doc.pop(k)
        else:
            doc[k] = v
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=message) as err:
        load_daemon_config(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_config_file_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="daemon config not found"):
        load_daemon_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("robot: [unclosed\n")
    with pytest.raises(ConfigError, match="invalid YAML at line"):
        load_daemon_config(bad)


def test_example_config_is_valid() -> None:
    root = Path(__file__).resolve().parents[2]
    cfg = load_daemon_config(root / "examples" / "link" / "daemon.yaml")
    assert set(cfg.campaigns) == {"nightly", "commissioning"}
    assert cfg.socket_mode == 0o660 and cfg.robot.is_file()


def test_a_full_disk_is_one_line_and_loses_nothing_already_stored(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, backend: Backend) -> None:
    import errno
    import os

    from robid_link.exceptions import StoreFullError
    from robid_link.link.store import files as store_mod

    st = backend.store(tmp_path / "state")
    kept = st.put_log(b"t,q1\n0,1\n")

    def no_room(*a: object, **kw: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(store_mod, "atomic_write", no_room)
    with pytest.raises(StoreFullError, match=r"state_dir: .*disk full while writing .*"
                                             r"waiting for space"):
        st.put_log(b"t,q1\n0,2\n")
    assert st.check_log(kept).read_bytes() == b"t,q1\n0,1\n"  # what was stored stays

    class Vfs:
        f_bavail, f_frsize = 10, 4096  # 40 kB free, below the reserve

    real_statvfs = os.statvfs
    monkeypatch.setattr(store_mod.os, "statvfs", lambda path: Vfs())
    with pytest.raises(StoreFullError, match=r"has 0 MiB free, 64 MiB needed for experiment "
                                             r"rb: waiting for space"):
        st.require_space(1000, "experiment rb")
    monkeypatch.setattr(store_mod.os, "statvfs", real_statvfs)
    st.require_space(1000, "experiment rb")  # space returned
    st.close()


def test_sqlite_disk_full_becomes_store_full(tmp_path: Path) -> None:
    """SQLite's own 'database or disk is full' (a page limit stands in for the disk)."""
    from robid_link.exceptions import StoreFullError
    from robid_link.link.store import Store

    st = Store(tmp_path / "state")
    run = st.create_run("quick", "operator", {}, [("a", "rigid_body")])

    def pragma(sql: str) -> int:
        with st.conn.begin():
            return int(st.conn.exec_driver_sql(sql).scalar())

    pages = pragma("PRAGMA page_count")
    pragma(f"PRAGMA max_page_count = {pages}")
    with pytest.raises(StoreFullError, match="disk full while writing"):
        for k in range(10_000):
            st.note(run, None, "filler", blob="x" * 4000, k=k)
    pragma("PRAGMA max_page_count = 1073741823")
    st.note(run, None, "after")  # the store works again
    st.close()
