"""The store as a plant's: a cell's SQLite store of the days before robots had names migrates
in place and keeps every row; one PostgreSQL database holds many robots, each daemon sees its
own runs, logs and approvals, and a robot is held by one daemon whatever its state dir; the
password comes from the environment, never from the URL; raw logs may live in a log store."""

from __future__ import annotations

import hashlib
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from robid_link.exceptions import ConfigError, StoreLockedError
from robid_link.link.store import Store
from robid_link.link.store.schema import SCHEMA_VERSION

from .conftest import Backend

#: the schema of the SQLite-only store (version 1), as its daemons created it
V1 = """
CREATE TABLE runs (run_id TEXT PRIMARY KEY, campaign TEXT NOT NULL, trigger TEXT NOT NULL,
    state TEXT NOT NULL, created REAL NOT NULL, started REAL, finished REAL,
    spec TEXT NOT NULL, error TEXT, step TEXT);
CREATE TABLE experiments (run_id TEXT NOT NULL, exp_id TEXT NOT NULL, position INTEGER NOT NULL,
    kind TEXT NOT NULL, state TEXT NOT NULL, attempt INTEGER NOT NULL DEFAULT 0,
    nonce TEXT, program_sha TEXT, done_sha TEXT, done_size INTEGER, log_sha TEXT,
    error TEXT, updated REAL NOT NULL, PRIMARY KEY (run_id, exp_id));
CREATE TABLE journal (seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL,
    run_id TEXT NOT NULL, exp_id TEXT, step TEXT NOT NULL, detail TEXT NOT NULL);
CREATE TABLE logs (sha256 TEXT PRIMARY KEY, size INTEGER NOT NULL, stored REAL NOT NULL);
CREATE TABLE programs (key TEXT PRIMARY KEY, sha256 TEXT NOT NULL, created REAL NOT NULL);
CREATE TABLE approvals (sha256 TEXT PRIMARY KEY, campaign TEXT NOT NULL, exp_id TEXT NOT NULL,
    approved REAL NOT NULL, by TEXT NOT NULL);
CREATE TABLE results (id INTEGER PRIMARY KEY AUTOINCREMENT, run_id TEXT NOT NULL,
    robot TEXT NOT NULL, kind TEXT NOT NULL, time REAL NOT NULL, record TEXT NOT NULL);
CREATE TABLE param_sets (sha256 TEXT PRIMARY KEY, robot TEXT NOT NULL, version INTEGER NOT NULL,
    run_id TEXT NOT NULL, created REAL NOT NULL, body BLOB NOT NULL, approved REAL,
    approved_by TEXT);
CREATE TABLE param_uploads (seq INTEGER PRIMARY KEY AUTOINCREMENT, robot TEXT NOT NULL,
    sha256 TEXT NOT NULL, time REAL NOT NULL, run_id TEXT, state TEXT NOT NULL, error TEXT);
INSERT INTO runs VALUES ('r1', 'quick', 'operator', 'running', 1.0, 2.0, NULL, '{}', NULL, 's');
INSERT INTO experiments VALUES ('r1', 'a', 0, 'rigid_body', 'stored', 1, 'n', 'p', 'd', 9,
    'LOGSHA', NULL, 3.0);
INSERT INTO journal (time, run_id, exp_id, step, detail) VALUES (1.0, 'r1', NULL, 'queued', '{}');
INSERT INTO logs VALUES ('LOGSHA', 9, 2.5);
INSERT INTO approvals VALUES ('PROG', 'quick', 'a', 1.5, 'op');
INSERT INTO results (run_id, robot, kind, time, record) VALUES ('r1', 'arm3', 'identify', 4.0,
    '{"rmse": [1.0]}');
INSERT INTO param_sets VALUES ('SET', 'arm3', 1, 'r1', 5.0, X'7B7D', NULL, NULL);
"""


def test_a_store_of_the_sqlite_days_migrates_in_place(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    db = sqlite3.connect(state / "robid.sqlite")
    db.executescript(V1)
    db.close()
    with pytest.raises(ConfigError, match=f"store schema version 1, this robid reads "
                                          f"{SCHEMA_VERSION}; start its daemon once to migrate "
                                          "it"):
        Store(state, readonly=True)
    with Store(state, robot="arm3") as st:  # the daemon: migrates, adopts the rows
        assert st.unfinished_runs() == ["r1"] and st.run("r1")["progress"]["stored"] == 1
        assert st.run("r1")["state_since"] == 1.0  # (v3) a run of before: since its creation
        assert st.log_count() == 1 and st.approved("PROG")
        assert st.results("arm3")[0]["record"] == {"rmse": [1.0]}
        assert st.param_set("arm3", "1")["body"] == b"{}"
        assert [j["step"] for j in st.journal("r1")] == ["queued"]
        run = st.create_run("quick", "operator", {}, [("a", "rigid_body")])
    with Store(state, readonly=True) as ro:
        assert {r["run_id"] for r in ro.runs()} == {"r1", run}
        assert all(r["robot"] == "arm3" for r in ro.runs())
        assert ro.identify_inputs("arm3") == []  # r1 never completed
    with Store(state, robot="arm3"):  # opened again: nothing left to migrate
        pass


def test_a_newer_store_is_refused(tmp_path: Path) -> None:
    Store(tmp_path / "s").close()
    db = sqlite3.connect(tmp_path / "s" / "robid.sqlite")
    db.execute("UPDATE robid_schema SET version = ?", (SCHEMA_VERSION + 1,))
    db.commit()
    db.close()
    with pytest.raises(ConfigError, match=fr"schema version {SCHEMA_VERSION + 1} is newer than "
                                          fr"this robid reads \({SCHEMA_VERSION}\); upgrade "
                                          r"robid_link"):
        Store(tmp_path / "s")


def test_robots_share_a_database_and_each_is_held_once(tmp_path: Path, pg_url: str) -> None:
    a = Store(tmp_path / "a", url=pg_url, robot="a")
    b = Store(tmp_path / "b", url=pg_url, robot="b")
    try:
        run_a = a.create_run("quick", "operator", {}, [("x", "rigid_body")])
        run_b = b.create_run("quick", "operator", {}, [("x", "rigid_body")])
        same = b"t,q1\n0,1\n"
        a.put_log(same)
        b.put_log(same)  # the same bytes in two cells: one row each, each in its own place
        a.approve("P", "quick", "x", "op")
        assert a.unfinished_runs() == [run_a] and b.unfinished_runs() == [run_b]
        assert a.log_count() == b.log_count() == 1
        assert a.approved("P") and not b.approved("P")  # an approval is per robot
        with pytest.raises(ConfigError, match="not in the store"):
            a.run(run_b)  # a daemon never touches another robot's run
        with pytest.raises(StoreLockedError, match=r"robot a is in use by another daemon "
                                                   r"\(pid \d+ on "):
            Store(tmp_path / "other", url=pg_url, robot="a")
        assert (tmp_path / "b" / "logs").is_dir() and a.log_path(
            hashlib.sha256(same).hexdigest()).is_file()
    finally:
        a.close()
        b.close()
    Store(tmp_path / "other", url=pg_url, robot="a").close()  # released with its session
    with Store(None, url=pg_url, readonly=True) as plant:
        assert sorted(r["robot"] for r in plant.runs()) == ["a", "b"]


def test_the_pages_views_read_a_plant_store_opened_by_its_url_alone(tmp_path: Path,
                                                                   pg_url: str) -> None:
    """A store opened by its URL has no cell folder, so no reports: the page's views said so
    with a TypeError (None / "reports"; found by mypy)."""
    from robid_link.web.views import run_view, runs_view

    with Store(tmp_path / "a", url=pg_url, robot="a") as a:
        run_id = a.create_run("quick", "operator", {}, [("x", "rigid_body")])
    with Store(None, url=pg_url, readonly=True) as plant:
        rows = runs_view(plant, "a")["runs"]
        assert [(r["run_id"], r["report"]) for r in rows] == [(run_id, False)]
        assert run_view(plant, run_id, "a")["report"] is None


def test_another_robots_parameter_set_is_refused_naming_both(tmp_path: Path,
                                                             backend: Backend) -> None:
    """Robot a's store may read robot b's sets (``params show``), but approving one was a
    silent no-op (the daemon then answered 'approved'): refused in one line naming both."""
    body = b'{"x": 1}'
    sha = hashlib.sha256(body).hexdigest()
    with backend.store(tmp_path / "b", robot="b") as b:
        run_b = b.create_run("cal", "operator", {}, [])
        b.add_param_set({"sha256": sha, "robot": "b", "run_id": run_b}, body)
    with backend.store(tmp_path / "a" if backend.url else tmp_path / "b", robot="a") as a:
        assert [s["sha256"] for s in a.param_sets("b")] == [sha]
        with pytest.raises(ConfigError, match=r"^parameter set 1 of robot b \(\w{12}\): this "
                                              r"store is robot a's; approve it with robot "
                                              r"b's daemon$"):
            a.approve_param_set(sha, "op")
        with pytest.raises(ConfigError, match=r"^parameter set 0{12}: not in the store$"):
            a.approve_param_set("0" * 64, "op")
    with backend.store(tmp_path / "b", robot="b") as b:
        assert b.param_sets("b")[0]["approved"] is None
        b.approve_param_set(sha, "op")
        assert b.param_sets("b")[0]["approved_by"] == "op"


def test_the_password_comes_from_the_environment(tmp_path: Path, pg_url: str,
                                                 postgres: object) -> None:
    """PGPASSWORD alone (no passfile) opens the store; a wrong one is one line."""
    Store(tmp_path / "s", url=pg_url, robot="r").close()
    code = ("import sys\nfrom robid_link.link.store import Store\n"
            "with Store(None, url=sys.argv[1], readonly=True) as s: print(len(s.runs()))\n")
    env = {k: v for k, v in os.environ.items() if k != "PGPASSFILE"}
    ok = subprocess.run([sys.executable, "-c", code, pg_url], capture_output=True, text=True,
                        env={**env, "PGPASSWORD": "robid-test-secret"}, timeout=60)
    assert ok.returncode == 0 and ok.stdout.strip() == "0", ok.stderr
    bad = subprocess.run([sys.executable, "-m", "robid_link.cli", "status", "--store", pg_url],
                         capture_output=True, text=True, env={**env, "PGPASSWORD": "nope"},
                         timeout=60)
    assert bad.returncode == 2 and "cannot connect" in bad.stderr and "password" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1 and "nope" not in bad.stderr


@pytest.mark.parametrize("url", [
    "postgresql://robid:s3cr3t-pw@db.plant:5432/robid",
    "postgresql://robid@db.plant:5432/robid?password=s3cr3t-pw",
    "postgresql+psycopg://robid@db.plant/robid?sslmode=require&PASSWORD=s3cr3t-pw",
    "postgres://robid@db.plant/robid?sslpassword=s3cr3t-pw",
])
def test_a_password_in_the_store_url_is_refused_unprinted(tmp_path: Path, url: str,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    """The password comes from PGPASSWORD or a PGPASSFILE: one in the URL (its user info or
    its query string) is refused in one line that does not print it, by the config, the
    store and ``--store``, before any connection."""
    from robid_link.cli import main
    from robid_link.config import load_daemon_config
    from tests.link.conftest import write_config

    with pytest.raises(ConfigError, match=r"daemon.yaml: store: the URL holds a password") as err:
        load_daemon_config(write_config(tmp_path, store=url))
    assert "s3cr3t" not in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=r"^store: the URL holds a password") as err:
        Store(None, url=url, readonly=True)
    assert "s3cr3t" not in str(err.value)
    assert main(["status", "--store", url]) == 2
    out, errors = capsys.readouterr()
    assert "s3cr3t" not in out + errors and len(errors.strip().splitlines()) == 1
    assert "the URL holds a password" in errors


def test_logs_in_a_central_log_store(tmp_path: Path) -> None:
    """``log_store``: a folder holds the logs instead of the state dir; an fsspec URL gets a
    copy of each before its row; the row says where."""
    import fsspec

    folder = tmp_path / "central"
    with Store(tmp_path / "s", robot="r", log_store=str(folder)) as st:
        sha = st.put_log(b"t,q1\n0,1\n")
        assert st.log_path(sha).is_relative_to(folder) and st.check_log(sha)
    with Store(tmp_path / "u", robot="r", log_store="memory://plant-logs") as st:
        sha = st.put_log(b"t,q1\n0,2\n")
        with fsspec.open(f"memory://plant-logs/logs/{sha[:2]}/{sha}.csv", "rb") as fh:
            assert fh.read() == b"t,q1\n0,2\n"
        run = st.create_run("q", "operator", {}, [("a", "rigid_body")])
        st.step(run, "a", "stored", log_sha=sha)
        st.set_run(run, "completed")
        (inputs,) = st.identify_inputs("r")
        assert inputs["logs"] == [{"sha256": sha, "url":
                                   f"memory://plant-logs/logs/{sha[:2]}/{sha}.csv"}]


def test_a_version_2_store_gains_state_since(tmp_path: Path) -> None:
    """Version 3: the time a run entered its state; the runs before read as their creation,
    an update that keeps the state keeps it, a change of state moves it."""
    with Store(tmp_path / "s") as st:
        run = st.create_run("quick", "operator", {}, [("a", "rigid_body")])
    db = sqlite3.connect(tmp_path / "s" / "robid.sqlite")
    db.execute("ALTER TABLE runs DROP COLUMN state_since")
    db.execute("UPDATE robid_schema SET version = 2")
    db.commit()
    db.close()
    with Store(tmp_path / "s") as st:
        created = st.run(run)["created"]
        assert st.run(run)["state_since"] == created
        st.set_run(run, "queued", step="still queued")
        assert st.run(run)["state_since"] == created
        st.set_run(run, "interrupted")
        assert st.run(run)["state_since"] > created
