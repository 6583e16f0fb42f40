"""The door between the link and the worker (``robid_link/jobs.py``): every record survives its
JSON, a record of another version, type or keys is refused in one line naming the record and
the key, and importing the door loads nothing numerical."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from typing import Any

import pytest

from robid_link import jobs as jb
from robid_link.exceptions import ModelError, RecordError

PROGRAM = jb.MotionProgram("rb-1", {"traj.csv": b"t,q1\n0,0\n0.01,0.001\n",
                                    "traj.yaml": b"rate_hz: 100\nkind: custom\n"},
                           0.01, {"kind": "rigid_body", "reduced_speed": 0.5})
PSET = jb.ParameterSet.from_doc({**(doc := {
    "format": jb.PARAMETER_SET_FORMAT, "robot": "arm3", "joints": ["j1", "j2"],
    "friction": {"viscous": [1.0, 2.0], "coulomb": [0.5, 0.5], "offset": [0.0, 0.0]},
    "standard_inertials": None, "ripple": []}), "sha256": jb.set_sha256(doc)})
HINT = jb.ResonanceHint(2, None, "add an elasticity experiment for joint 2")
INFO = jb.RobotInfo("arm3", ("j1", "j2"), ("revolute", "prismatic"), (-1.0, -0.5),
                    (1.0, 0.5), (2.0, 1.0), (10.0, math.inf), (50.0, math.inf))
FLAG = jb.DriftFlag("r1", "fv_1", "friction", 0.25, 7.5, "fv_1: friction up 25 %")

#: one instance of every record type (a new record needs one here: see the first test)
SAMPLES: dict[str, jb.Record] = {r.TYPE: r for r in (
    INFO, PROGRAM, PSET, HINT, FLAG,
    jb.RobotInfoJob("/etc/robid/arm3.yaml", ("gripper",)),
    jb.ProgramJob("arm3.yaml", (), "rb-1", "rigid_body", {"duration_s": 10.0, "joints": None},
                  "/etc/robid", 0.5),
    jb.LogCheckJob("/var/lib/robid/logs/ab.csv", 3),
    jb.LogCheck(2500, 9.996, 250.0),
    jb.ModelCheckJob(None, ("coulomb@2", "ripple@3")),
    jb.ModelCheck(("rigid_body", "viscous", "coulomb")),
    jb.IdentifyJob("r1", "arm3.yaml", (), ("a.csv", "b.csv"), "/tmp/rep", "model.yaml",
                   ("coulomb@2",), "ols", True, 20.0, False, True, (HINT,)),
    jb.IdentifyOutcome("arm3", {"identify": {"rmse": [0.1, float("nan")]}}, "summary", PSET),
    jb.VerifyRun("verify-before", "before", "v.csv", PROGRAM),
    jb.VerifyJob("arm3.yaml", (), (jb.VerifyRun("verify", "after", "v.csv", PROGRAM),)),
    jb.VerifyOutcome("arm3", ({"kind": "verify", "tracking": {"tool_rms_mm": 0.05}},)),
    jb.ElasticityRun("stiff", "e.csv", PROGRAM),
    jb.ElasticityJob("arm3.yaml", (), (jb.ElasticityRun("stiff", "e.csv", PROGRAM),)),
    jb.ElasticityOutcome("arm3", ({"experiment": "stiff", "result": {"joints": []}},)),
    jb.FeedforwardJob("arm3.yaml", (), PSET, 0.004, ((0.0, 0.1), (0.001, 0.1))),
    jb.FeedforwardTable(PSET.sha256, 0.004, ((1.5, -2.0), (1.5, -2.25))),
    jb.DriftJob("arm3", ({"kind": "identify", "run_id": "r1"},), None),
    jb.DriftReport((FLAG,)),
)}


def test_every_record_has_a_sample() -> None:
    assert sorted(SAMPLES) == sorted(jb.RECORDS)


@pytest.mark.parametrize("name", sorted(jb.RECORDS))
def test_json_round_trip_of_every_record(name: str) -> None:
    rec = SAMPLES[name]
    text = rec.to_json()
    doc = json.loads(text)
    assert (doc["schema"], doc["type"]) == (jb.SCHEMA, name)
    back = type(rec).from_json(text)
    assert type(back) is type(rec)
    assert back.to_json() == text  # NaN compares unequal: compare the wire form
    if name != "identify-outcome":
        assert back == rec
    assert type(jb.Record.from_json(text)) is type(rec)  # the type names the class


def test_program_bytes_and_unknown_limits_survive_exactly() -> None:
    back = jb.MotionProgram.from_json(PROGRAM.to_json())
    assert back.files == PROGRAM.files and back.sha256 == PROGRAM.sha256
    assert jb.RobotInfo.from_json(INFO.to_json()).tau_max[1] == math.inf
    assert jb.IdentifyJob.from_json(SAMPLES["identify-job"].to_json()).resonance_hints == (HINT,)


def _wire(name: str, **change: Any) -> str:
    doc = SAMPLES[name].to_dict()
    for key, value in change.items():
        if value is None:
            del doc[key]
        else:
            doc[key] = value
    return json.dumps(doc)


@pytest.mark.parametrize(("text", "message"), [
    (_wire("log-check-job", schema="robid-job/2"),
     "record: schema 'robid-job/2' unknown (this side reads robid-job/1)"),
    (_wire("log-check-job", schema=None), "record: key 'schema' missing"),
    (_wire("log-check-job", type="warp-job"), "record: type 'warp-job' unknown"),
    (_wire("log-check-job", colour="red"),
     "log-check-job: unknown key 'colour' (known: log, n_joints)"),
    (_wire("log-check-job", n_joints=None), "log-check-job: key 'n_joints' missing"),
    (_wire("log-check-job", n_joints="3"), "log-check-job: key 'n_joints': expected an "
                                           "integer, got '3'"),
    (_wire("identify-job", resonance_hints=[{"joint": 2, "todo": "x"}]),
     "identify-job: key 'resonance_hints[0].measured_by' missing"),
    (_wire("verify-job", runs=[{**SAMPLES["verify-run"].to_dict(), "program": {
        **PROGRAM.to_dict(), "files": {"traj.csv": "not base64!"}}}]),
     "verify-job: unknown key 'runs[0].schema'"),
    (_wire("feedforward-table", tau=[[1.0, 2.0], [1.0, "2"]]),
     "feedforward-table: key 'tau[1][1]': expected a number, got '2'"),
    (_wire("model-check", effects=["rigid_body", True]),
     "model-check: key 'effects[1]': expected a string, got True"),
    ("[1, 2]", "record: expected a JSON object, got a list"),
    ("{", "record: not JSON"),
])
def test_a_foreign_record_is_refused_in_one_line(text: str, message: str) -> None:
    with pytest.raises(RecordError) as err:
        jb.Record.from_json(text)
    assert str(err.value).startswith(message)
    assert "\n" not in str(err.value)


def test_nested_keys_and_bytes_are_named() -> None:
    run = {k: v for k, v in SAMPLES["verify-run"].to_dict().items()
           if k not in ("schema", "type")}
    run["program"] = {k: v for k, v in PROGRAM.to_dict().items() if k not in ("schema", "type")}
    run["program"]["files"] = {"traj.csv": "not base64!"}
    with pytest.raises(RecordError, match=r"verify-job: key 'runs\[0\]\.program\.files\."
                                          r"traj\.csv': expected base64 text"):
        jb.VerifyJob.from_json(_wire("verify-job", runs=[run]))


def test_a_record_of_another_type_is_refused_where_one_type_is_expected() -> None:
    with pytest.raises(RecordError, match="log-check: expected a motion-program record"):
        jb.MotionProgram.from_json(SAMPLES["log-check"].to_json())


def test_parameter_set_is_checked_without_numpy() -> None:
    with pytest.raises(ModelError, match=r"damaged \(sha256 mismatch\)"):
        jb.ParameterSet.from_doc({**PSET.doc, "robot": "other"})
    with pytest.raises(ModelError, match="format 'x'"):
        jb.ParameterSet.from_doc({**PSET.doc, "format": "x"})
    PSET.check(2)
    with pytest.raises(ModelError, match="sizes do not fit a 3-joint robot"):
        PSET.check(3)


def test_importing_the_door_loads_nothing_numerical() -> None:
    code = ("import sys, robid_link.jobs, robid_link.kinds, robid_link.config, "
            "robid_link.link.worker\n"
            "bad = sorted(m for m in ('numpy', 'scipy', 'pinocchio', 'robid_link.ident') "
            "if m in sys.modules)\n"
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == ""


def test_the_worker_entry_answers_through_the_door() -> None:
    """``run_here``: the job's JSON into the entry point named in WORKER_ENTRY (imported by
    name), the answer parsed into the record the job expects; the entry refuses a job of
    another version as the link refuses an answer of one."""
    from robid_link.ident.entry import run
    from robid_link.link.worker import run_here

    out = run_here(jb.ModelCheckJob(None, ("coulomb@2",)))
    assert isinstance(out, jb.ModelCheck) and "rigid_body" in out.effects
    assert any("coulomb" in e for e in out.effects)
    with pytest.raises(ModelError):
        run_here(jb.ModelCheckJob(None, ("warp@1",)))
    with pytest.raises(RecordError, match="schema 'robid-job/2' unknown"):
        run(_wire("model-check-job", schema="robid-job/2"))


def test_a_numerical_job_loads_the_numerical_modules_without_the_collector() -> None:
    """The worker process's side of the door: a job that computes (here: drift over no
    records) loads numba's compiler with the collector off and freezes what it loaded (the
    collector on again after); a job that only reads a file freezes nothing. A fresh
    process each, as the daemon's workers are."""
    code = ("import gc, sys\nfrom robid_link import jobs as jb\nfrom robid_link.ident.entry "
            "import run\njob = {job}\nprint(jb.Record.from_json(run(job.to_json())).TYPE, "
            "gc.isenabled(), gc.get_freeze_count() > 0)\n")
    cases = {"jb.DriftJob('arm3', (), None)": "drift-report True True",
             "jb.ModelCheckJob(None, ('coulomb',))": "model-check True False"}
    for job, expected in cases.items():
        out = subprocess.run([sys.executable, "-c", code.format(job=job)], capture_output=True,
                             text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert out.stdout.split("\n")[-2] == expected, (job, out.stdout)
