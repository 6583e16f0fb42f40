"""Fuzz every loader and the CLI's options with generated malformed inputs (issue 14).

Each generated input is malformed by construction. Every case must end in one ``RobidError``
of one line naming the file (exit code 2 and one stderr line for the CLI): any other exception
is a traceback, more than ``CASE_S`` seconds a hang, and a return a wrong success.
``make test`` runs a short version; ``make validate`` (ROBID_VALIDATE=1, -m slow) ≥ 1000 cases.
"""

from __future__ import annotations

import copy
import io
import json
import os
import signal
import time
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robid_link.cli import main
from robid_link.config import load_daemon_config
from robid_link.exceptions import RobidError
from robid_link.fakes.plant import load_truth
from robid_link.ident.data.logs import load_log
from robid_link.ident.diagnosis.history import history_path, read_history
from robid_link.ident.excite.excitation import read_trajectory
from robid_link.ident.model.effects import load_model
from robid_link.ident.model.robot import load_robot

from .conftest import ROBOTS

SLOW = bool(os.environ.get("ROBID_VALIDATE"))
#: examples per file kind or option family: 12 kinds × 100 ≥ 1000 in make validate
EXAMPLES = 100 if SLOW else 9
CASE_S = 20
COUNTS: Counter[str] = Counter()
FAILURES: list[str] = []
ARM3 = yaml.safe_load((ROBOTS / "arm3.yaml").read_text())
N = 3


class _Hang(Exception):
    pass


def _alarm(signum: int, frame: Any) -> None:
    raise _Hang


def check(kind: str, name: Path | str, run: Callable[[], Any]) -> None:
    """Run one malformed case: it must raise a one-line RobidError naming ``name``."""
    COUNTS[kind] += 1
    old_handler = signal.signal(signal.SIGALRM, _alarm)
    prev, _ = signal.setitimer(signal.ITIMER_REAL, CASE_S)  # pytest-timeout's alarm, restored
    start = time.monotonic()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run()
    except _Hang:
        FAILURES.append(f"{kind}: hang (> {CASE_S} s) on {name}")
        pytest.fail(FAILURES[-1])
    except RobidError as err:
        msg = str(err)
        if "\n" in msg or str(name) not in msg:
            FAILURES.append(f"{kind}: message not one line naming {name}: {msg!r}")
            pytest.fail(FAILURES[-1])
    except Exception as err:  # a traceback for the user
        FAILURES.append(f"{kind}: traceback {type(err).__name__}: {err}"[:300])
        raise
    else:
        FAILURES.append(f"{kind}: wrong success on {name}")
        pytest.fail(FAILURES[-1])
    finally:
        elapsed = time.monotonic() - start
        signal.setitimer(signal.ITIMER_REAL, max(prev - elapsed, 0.001) if prev else 0)
        signal.signal(signal.SIGALRM, old_handler)


def check_cli(kind: str, argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    def run() -> None:
        rc = main(argv)
        err = [line for line in capsys.readouterr().err.strip().splitlines()
               if not line.startswith("robid: warning:")]
        if rc == 0:
            return  # check() counts it as a wrong success
        if rc != 2 or len(err) != 1 or not err[0].startswith("robid: error: "):
            raise AssertionError(f"exit {rc}, stderr {err!r}")
        raise RobidError(err[0])

    check(kind, "robid: error:", run)


FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                suppress_health_check=list(HealthCheck))
#: slow: selected by make validate (-m slow), where ROBID_VALIDATE raises the example count;
#: make test runs the same tests with a few examples each
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@pytest.fixture(scope="module")
def arm3_robot():
    return load_robot(ROBOTS / "arm3.yaml")


# ----------------------------------------------------------------------------- generators

not_a_number = st.one_of(
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 10 ** 400, -(10 ** 400)]),
    st.text(max_size=8), st.none(), st.booleans(), st.lists(st.integers(), max_size=2),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))
json_like = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10)),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.text(max_size=6), children, max_size=4), max_leaves=20)


def _set(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    doc = copy.deepcopy(doc)
    target = doc
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return doc


def alias_bomb(levels: int) -> str:
    text = 'a0: &a0 ["x","x","x","x","x","x","x","x","x","x"]\n'
    for i in range(1, levels):
        text += f"a{i}: &a{i} [{','.join([f'*a{i - 1}'] * 10)}]\n"
    return text


def yaml_junk() -> st.SearchStrategy[str]:
    """Documents that no YAML file kind of the tool accepts."""
    return st.one_of(
        st.integers(6, 12).map(alias_bomb),
        st.integers(40, 200).map(lambda d: "[" * d + "]" * d),
        json_like.filter(lambda v: not isinstance(v, dict) or v and "effects" not in v).map(
            lambda v: yaml.safe_dump(v)),
        st.binary(min_size=1, max_size=64).map(lambda b: b.decode("latin-1") + "\x00: [\n"),
        st.sampled_from(["a: 2024-13-45\n", "a: [\n", "{a: 1\n", "a: !!python/object:os.system"
                         " x\n", "- &x [*x]\n", "a: *missing\n", "? [1]\n: 2\n"]))


def robot_bad() -> st.SearchStrategy[str]:
    j = st.integers(0, N - 1)
    mutations = st.one_of(
        st.tuples(j, st.sampled_from(["alpha", "a", "theta", "d"]), not_a_number).map(
            lambda m: _set(ARM3, ("joints", m[0], m[1]), m[2])),
        st.tuples(j, st.floats(-200, 200)).map(
            lambda m: _set(ARM3, ("joints", m[0], "limits", "q"), [m[1], m[1]])),
        st.tuples(j, st.floats(-1e6, 0)).map(
            lambda m: _set(ARM3, ("joints", m[0], "limits", "tau"), m[1])),
        st.tuples(j, st.floats(-1e6, -1e-3)).map(
            lambda m: _set(ARM3, ("joints", m[0], "inertial", "m"), m[1])),
        st.tuples(j, st.floats(-10, -1e-3)).map(
            lambda m: _set(ARM3, ("joints", m[0], "inertial", "I"), [m[1], 0, 0.1, 0, 0, 0.1])),
        st.tuples(j).map(lambda m: _set(ARM3, ("joints", m[0], "limits"), {"qd": 10})),
        st.tuples(st.floats(1.01, 2.99).filter(lambda x: x != 2), not_a_number).map(
            lambda m: _set(ARM3, ("transmission",),
                           {"ratios": [10, 10, 10], "coupling": [[1, m[0], 1.0]]})),
        json_like.map(lambda v: _set(ARM3, ("joints",), v)).filter(
            lambda d: not isinstance(d["joints"], list) or not d["joints"]),
    )
    return st.one_of(mutations.map(yaml.safe_dump), yaml_junk())


URDF_OK = {"mass": "1.0", "ixx": "0.01", "lower": "-1", "upper": "1", "effort": "10",
           "velocity": "2"}


def urdf_text(**over: str) -> str:
    v = {**URDF_OK, **over}
    return (f'<robot name="r"><link name="base"/><link name="l1"><inertial><mass '
            f'value="{v["mass"]}"/><inertia ixx="{v["ixx"]}" ixy="0" ixz="0" iyy="0.01" iyz="0" '
            f'izz="0.01"/></inertial></link><joint name="j1" type="revolute"><parent link="base"/>'
            f'<child link="l1"/><axis xyz="0 0 1"/><limit lower="{v["lower"]}" '
            f'upper="{v["upper"]}" effort="{v["effort"]}" velocity="{v["velocity"]}"/></joint>'
            "</robot>")


def urdf_bad() -> st.SearchStrategy[str]:
    word = st.sampled_from(["nan", "inf", "-inf", "", "x", "1e999", "1,0", "--1"])
    neg = st.floats(-1e6, -1e-6).map(repr)
    good = urdf_text()
    return st.one_of(
        st.tuples(st.sampled_from(list(URDF_OK)), word).map(lambda m: urdf_text(**{m[0]: m[1]})),
        st.sampled_from(["mass", "effort", "velocity"]).flatmap(
            lambda k: neg.map(lambda v: urdf_text(**{k: v}))),
        st.sampled_from(["effort", "velocity"]).map(lambda k: urdf_text(**{k: "0"})),
        st.floats(-3, 3).map(lambda x: urdf_text(lower=repr(x), upper=repr(x))),
        st.floats(0.021, 100).map(lambda x: urdf_text(ixx=repr(x))),
        st.integers(0, len(good) - 2).map(lambda k: good[:k]),
        st.sampled_from(['<!DOCTYPE r [<!ENTITY a "aaaaaaaaaa">]><robot name="r">&a;</robot>',
                         "<robot/>", "<robt/>", "\xff\xfe", "<robot><link/></robot>"]))


CSV_HEADER = ["t", "q1", "q2", "q3", "tau1", "tau2", "tau3"]


def _csv(rows: list[list[str]], header: list[str] = CSV_HEADER) -> str:
    return "\n".join(",".join(r) for r in [header, *rows]) + "\n"


def _rows(k: int = 20) -> list[list[str]]:
    return [[f"{0.01 * i:.2f}"] + ["0.1"] * 6 for i in range(k)]


def csv_bad() -> st.SearchStrategy[bytes]:
    cell = st.tuples(st.integers(0, 19), st.integers(1, 6))
    bad_cell = st.one_of(st.sampled_from(["nan", "inf", "-inf", "", "x", "1e999", "0x10"]),
                         st.text(min_size=1, max_size=6).filter(lambda s: not _is_float(s)))

    def with_cell(m: tuple[tuple[int, int], str]) -> str:
        rows = _rows()
        rows[m[0][0]][m[0][1]] = m[1].replace(",", ";").replace("\n", " ").replace('"', "")
        return _csv(rows)

    def ragged(i: int) -> str:
        rows = _rows()
        rows[i] = rows[i][:-1]
        return _csv(rows)

    def dup_time(i: int) -> str:
        rows = _rows()
        rows[i + 1][0] = rows[i][0]
        return _csv(rows)

    return st.one_of(
        st.tuples(cell, bad_cell).map(with_cell),
        st.integers(0, 19).map(ragged),
        st.integers(0, 18).map(dup_time),
        st.integers(0, 9).map(lambda k: _csv(_rows(k))),
        # t or a position dropped (a log without some torques is a partial log, no error)
        st.integers(0, 3).map(lambda k: _csv([r[:k] + r[k + 1:] for r in _rows()],
                                             CSV_HEADER[:k] + CSV_HEADER[k + 1:])),
        st.just(_csv([r[:4] for r in _rows()], CSV_HEADER[:4])),  # no torque at all
        st.sampled_from(["qd1", "q4", "tau9", "t", "x"]).map(
            lambda h: _csv([r + ["0"] for r in _rows()], [*CSV_HEADER, h])),
        st.integers(140_000, 300_000).map(lambda k: _csv(_rows()) + '"' + "1" * k + '"\n'),
    ).map(str.encode) | st.binary(max_size=64).map(lambda b: b"\xff\x00" + b)


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _npz(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


GOOD_NPZ = _npz(t=np.arange(20) * 0.01, q=np.zeros((20, N)), tau=np.zeros((20, N)))


def _huge_npz(shape: tuple[int, ...]) -> bytes:
    import zipfile

    npy = io.BytesIO()
    np.lib.format.write_array_header_1_0(npy, {"descr": "<f8", "fortran_order": False,
                                               "shape": shape})
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("t.npy", npy.getvalue() + b"\0" * 64)
    return buf.getvalue()


def npz_bad() -> st.SearchStrategy[bytes]:
    t = np.arange(20) * 0.01
    return st.one_of(
        st.integers(0, len(GOOD_NPZ) - 1).map(lambda k: GOOD_NPZ[:k]),
        st.integers(1 << 28, 1 << 50).map(lambda k: _huge_npz((k, 8))),
        st.sampled_from(["t", "q", "tau"]).map(lambda k: _npz(**{
            **{"t": t, "q": np.zeros((20, N)), "tau": np.zeros((20, N))},
            k: np.array(["a"] * 20)})),
        st.sampled_from(["t", "q", "tau"]).map(lambda k: _npz(**{
            n: v for n, v in {"t": t, "q": np.zeros((20, N)), "tau": np.zeros((20, N))}.items()
            if n != k})),
        st.tuples(st.integers(0, 19), st.sampled_from([np.nan, np.inf])).map(
            lambda m: _npz(t=t, q=np.where(np.arange(20)[:, None] == m[0], m[1],
                                           np.zeros((20, N))), tau=np.zeros((20, N)))),
        st.integers(1, 6).filter(lambda k: k != N).map(
            lambda k: _npz(t=t, q=np.zeros((20, k)), tau=np.zeros((20, k)))),
        st.sampled_from([np.float64(1.0), np.zeros(5), np.zeros((20, N, 2)),
                         np.zeros((20, N), complex)]).map(
            lambda a: _npz(t=t, q=a, tau=np.zeros((20, N)))),
        st.binary(max_size=200))


def mat_bad() -> st.SearchStrategy[bytes]:
    import scipy.io

    buf = io.BytesIO()
    scipy.io.savemat(buf, {"m": np.zeros((30, 4 * N))}, do_compression=True)
    good = buf.getvalue()

    def saved(doc: dict[str, Any]) -> bytes:
        out = io.BytesIO()
        scipy.io.savemat(out, doc)
        return out.getvalue()

    return st.one_of(
        st.integers(0, len(good) - 1).map(lambda k: good[:k]),
        st.sampled_from([{"m": np.zeros((30, 5))}, {"m": np.zeros((30, 12)), "n": np.ones((4, 2))},
                         {"m": np.array(["abc"])}, {"m": np.zeros((30, 12), complex)},
                         {"m": np.full((30, 12), np.nan)}]).map(saved),
        st.binary(max_size=300).map(lambda b: b"MATLAB 5.0 MAT-file" + b))


def model_bad() -> st.SearchStrategy[str]:
    entry = st.one_of(
        st.text(max_size=10).filter(lambda s: not _valid_entry(s)),
        st.sampled_from(["viscous@", "viscous@0", "viscous@-1", "rigid_body@1", "viscous@1.5",
                         "viscous@" + "9" * 30]),
        st.tuples(st.sampled_from(["spring", "ripple", "stribeck", "friction_power",
                                   "friction_drift", "delay"]),
                  st.sampled_from(["order", "period", "vs", "alpha", "tau_s", "seconds"]),
                  st.one_of(not_a_number, st.sampled_from([0, -1, 1e12, -1e12]))).map(
            lambda m: {"name": m[0], m[1]: m[2]} if m[0] != "delay" else {"name": m[0], m[1]:
                                                                         1e9}),
        json_like.filter(lambda v: not isinstance(v, str) and not _valid_entry(v)))

    def doc(entries: list[Any]) -> str:
        return yaml.safe_dump({"effects": ["rigid_body", *entries]})

    return st.one_of(st.lists(entry, min_size=1, max_size=3).map(doc),
                     st.sampled_from(["effects: []\n", "effects: [offset]\n", "effects: 5\n"]),
                     yaml_junk())


TRUTH_OK = {"effects": [{"name": "viscous", "fv": 1.0}], "noise": {"tau": 0.1},
            "rate_hz": 500}


def _valid_entry(entry: Any) -> bool:
    from robid_link.ident.model.effects import parse_effect

    try:
        parse_effect(entry)
    except RobidError:
        return False
    return True


def truth_bad() -> st.SearchStrategy[str]:
    return st.one_of(
        st.tuples(st.sampled_from([("rate_hz",), ("noise", "tau"), ("noise", "q_resolution"),
                                   ("effects", 0, "fv")]), not_a_number).map(
            lambda m: yaml.safe_dump(_set(TRUTH_OK, m[0], m[1]))),
        st.sampled_from([0, -1, 1e9]).map(lambda v: yaml.safe_dump(_set(TRUTH_OK, ("rate_hz",),
                                                                         v))),
        json_like.map(lambda v: yaml.safe_dump({**TRUTH_OK, "inertials": v})),
        json_like.filter(lambda v: v is not None and v != {}).map(
            lambda v: yaml.safe_dump({**TRUTH_OK, "perturb": v if not isinstance(v, dict)
                                      else {**v, "zz": 1}})),
        st.floats(-1e3, -1e-3).map(lambda m: yaml.safe_dump({**TRUTH_OK, "inertials": [
            [m] + [0.0] * 9, [1.0, 0, 0, 0, 0.1, 0, 0.1, 0, 0, 0.1],
            [1.0, 0, 0, 0, 0.1, 0, 0.1, 0, 0, 0.1]]})),
        json_like.filter(lambda v: not isinstance(v, list) or v).map(
            lambda v: yaml.safe_dump({**TRUTH_OK, "effects": [v]})),
        yaml_junk())


def trajectory_bad() -> st.SearchStrategy[tuple[str, str]]:
    good_csv = "t,q1,q2,q3\n" + "".join(f"{k * 0.004:.3f},0,0,0\n" for k in range(10))
    good_yaml = "rate_hz: 250\nkind: custom\n"
    return st.one_of(
        not_a_number.map(lambda v: (good_csv, yaml.safe_dump({"rate_hz": v, "kind": "custom"}))),
        st.sampled_from([0, -5, 1e9]).map(
            lambda v: (good_csv, yaml.safe_dump({"rate_hz": v, "kind": "custom"}))),
        json_like.filter(lambda v: v not in ("fourier", "sweep", "stepped_sine", "custom")).map(
            lambda v: (good_csv, yaml.safe_dump({"rate_hz": 250, "kind": v}))),
        csv_bad().map(lambda b: (b.decode("latin-1"), good_yaml)),
        st.integers(0, 1).map(lambda k: (good_csv.splitlines()[0] + "\n"
                                         + good_csv.splitlines()[1] * k, good_yaml)),
        st.tuples(not_a_number, st.sampled_from(["base_hz", "q0", "a", "b"])).map(
            lambda m: (good_csv, yaml.safe_dump({"rate_hz": 250, "kind": "fourier", "base_hz":
                                                 0.1, "q0": [0] * 3, "a": [[0]] * 3,
                                                 "b": [[0]] * 3, m[1]: m[0]}))),
        yaml_junk().map(lambda y: (good_csv, y)))


def history_bad() -> st.SearchStrategy[bytes]:
    record = {"time": "2024-01-01T00:00:00", "kind": "identify", "effects": ["rigid_body"],
              "rmse": [0.1, 0.2, 0.3]}
    return st.one_of(
        json_like.filter(lambda v: not isinstance(v, dict)).map(json.dumps),
        st.tuples(st.sampled_from(["time", "kind", "effects", "rmse", "suggestions"]),
                  st.one_of(st.integers(), st.lists(st.text(max_size=2), min_size=1,
                                                    max_size=2), st.booleans())).filter(
            lambda m: not (m[0] == "effects" and isinstance(m[1], list))).map(
            lambda m: json.dumps({**record, m[0]: m[1]})),
        st.text(max_size=20).filter(lambda s: not _is_json(s)),
        st.integers(1000, 100_000).map(lambda d: "[" * d),
        st.just(""), st.just("\n\n"),
    ).map(str.encode) | st.binary(min_size=1, max_size=30).map(lambda b: b"\xff" + b)


def _is_json(s: str) -> bool:
    try:
        json.loads(s)
    except ValueError:
        return False
    return True


CONFIG_OK = {"robot": str(ROBOTS / "arm3.yaml"), "state_dir": "state", "control_socket": "c.sock",
             "driver": {"name": "file_share", "share": "share"},
             "campaigns": {"a": {"experiments": ["rigid_body"]}}}


def config_bad() -> st.SearchStrategy[str]:
    return st.one_of(
        st.tuples(st.sampled_from(["robot", "state_dir", "control_socket"]),
                  json_like.filter(lambda v: not isinstance(v, str) or not v)).map(
            lambda m: yaml.safe_dump(_set(CONFIG_OK, (m[0],), m[1]))),
        json_like.filter(lambda v: not isinstance(v, dict) or not v).map(
            lambda v: yaml.safe_dump(_set(CONFIG_OK, ("campaigns",), v))),
        st.tuples(st.sampled_from(["retries", "backoff_s", "timeout_s", "cutoff_hz", "method",
                                   "experiments", "reduced_speed_first"]),
                  st.one_of(not_a_number.filter(lambda v: v is not None), st.just(-1))).map(
            lambda m: yaml.safe_dump(_set(CONFIG_OK, ("campaigns", "a", m[0]), m[1]))),
        st.sampled_from(list(CONFIG_OK)).map(
            lambda k: yaml.safe_dump({x: v for x, v in CONFIG_OK.items() if x != k})),
        yaml_junk())


OPTIONS: dict[str, tuple[list[str], bool]] = {
    # option: (argv before it, integer option)
    "--cutoff": (["identify", "--robot", "R", "--data", "x.csv"], False),
    "--fs": (["diagnose", "--robot", "R", "--data", "x.csv"], False),
    "--interval": (["identify", "--robot", "R", "--data", "x.csv"], True),
    "--rate": (["excite", "--robot", "R", "--out", "t.csv"], False),
    "--duration": (["excite", "--robot", "R", "--out", "t.csv"], False),
    "--base-hz": (["excite", "--robot", "R", "--out", "t.csv"], False),
    "--harmonics": (["excite", "--robot", "R", "--out", "t.csv"], True),
    "--evaluations": (["excite", "--robot", "R", "--out", "t.csv"], True),
    "--seed": (["simulate", "--robot", "R", "--truth", "T", "--trajectory", "X", "--out",
                "l.csv"], True),
    "--fault-count": (["fake-controller", "--share", ".", "--robot", "R"], True),
    "--q": (["show-robot", "--robot", "R", "--out", "x.png"], False),
}


def option_bad() -> st.SearchStrategy[tuple[str, str]]:
    bad_float = st.one_of(st.sampled_from(["nan", "inf", "-inf", "1e999", "-1", "0", "", "x",
                                           "1e10", "0x1p3", "1/2"]),
                          st.floats(max_value=-1e-9).map(repr),
                          st.text(max_size=6).filter(lambda s: not _is_float(s)))
    bad_int = st.one_of(st.sampled_from(["1.5", "1e3", "-1", "9" * 30, "nan", "inf", "", "x",
                                         "0x10", " ", "1_0", "٣"]),
                        st.integers(10 ** 20, 10 ** 40).map(str),
                        st.text(max_size=6).filter(lambda s: not s.strip().isdigit()))
    not_finite = st.one_of(st.sampled_from(["nan", "inf", "-inf", "1e999", "x", "", "1e10"]),
                           st.text(max_size=6).filter(lambda s: not _is_float(s)))

    def values(o: str) -> st.SearchStrategy[str]:
        return bad_int if OPTIONS[o][1] else not_finite if o == "--q" else bad_float

    return st.sampled_from(sorted(OPTIONS)).flatmap(lambda o: values(o).map(lambda v: (o, v)))


# ----------------------------------------------------------------------------- the fuzz tests

def _write(path: Path, data: bytes | str) -> Path:
    path.write_bytes(data.encode("utf-8", "surrogateescape") if isinstance(data, str) else data)
    return path


@FUZZ
@given(text=robot_bad())
def test_fuzz_robot_yaml(work, text):
    p = _write(work / "robot.yaml", text)
    check("robot YAML", p, lambda: load_robot(p))


@FUZZ
@given(text=urdf_bad())
def test_fuzz_urdf(work, text):
    p = _write(work / "robot.urdf", text)
    check("URDF", p, lambda: load_robot(p))


@FUZZ
@given(data=csv_bad())
def test_fuzz_log_csv(work, data):
    p = _write(work / "log.csv", data)
    check("log CSV", p, lambda: load_log(p, N))


@FUZZ
@given(data=npz_bad())
def test_fuzz_log_npz(work, data):
    p = _write(work / "log.npz", data)
    check("log npz", p, lambda: load_log(p, N))


@FUZZ
@given(data=mat_bad())
def test_fuzz_log_mat(work, data):
    p = _write(work / "log.mat", data)
    check("log .mat", p, lambda: load_log(p, N, fs=100.0))


@FUZZ
@given(text=model_bad())
def test_fuzz_model(work, text):
    p = _write(work / "model.yaml", text)
    check("model YAML", p, lambda: load_model(p))


@FUZZ
@given(text=truth_bad())
def test_fuzz_truth(work, arm3_robot, text):
    p = _write(work / "truth.yaml", text)
    check("truth YAML", p, lambda: load_truth(p, arm3_robot))


@FUZZ
@given(files=trajectory_bad())
def test_fuzz_trajectory(work, files):
    p = _write(work / "traj.csv", files[0])
    _write(work / "traj.yaml", files[1])
    check("trajectory", "traj.", lambda: read_trajectory(p))


@FUZZ
@given(data=history_bad())
def test_fuzz_history(work, data):
    m = work / "model.yaml"
    _write(history_path(m), data)
    check("history", history_path(m).name, lambda: read_history(m))


@FUZZ
@given(text=config_bad())
def test_fuzz_daemon_config(work, text):
    p = _write(work / "daemon.yaml", text)
    check("daemon config", p, lambda: load_daemon_config(p))


@FUZZ
@given(case=option_bad())
def test_fuzz_cli_options(case, capsys):
    option, value = case
    before, _ = OPTIONS[option]
    argv = [str(ROBOTS / "arm3.yaml") if a == "R" else a for a in before]
    extra = ["0", "0"] if option == "--q" else []
    check_cli(f"CLI {option}", [*argv, option, *extra, value] if option != "--q"
              else [*argv, option, value, *extra], capsys)


@FUZZ
@given(name=st.sampled_from(["robot", "model", "truth", "trajectory"]), text=yaml_junk())
def test_fuzz_cli_files(work, capsys, name, text):
    arm3 = str(ROBOTS / "arm3.yaml")
    p = _write(work / f"cli-{name}.yaml", text)
    if name == "trajectory":
        _write(work / "cli-trajectory.csv", "t,q1,q2,q3\n0,0,0,0\n0.004,0,0,0\n")
    truth = _write(work / "cli-truth-ok.yaml", "{}\n") if name != "truth" else p
    argv = {"robot": ["show-robot", "--robot", str(p), "--out", str(work / "r.png")],
            "model": ["excite", "--robot", arm3, "--model", str(p), "--out",
                      str(work / "t.csv")],
            "truth": ["simulate", "--robot", arm3, "--truth", str(truth), "--trajectory",
                      str(work / "none.csv"), "--out", str(work / "l.csv")],
            "trajectory": ["simulate", "--robot", arm3, "--truth", str(truth), "--trajectory",
                           str(work / "cli-trajectory.csv"), "--out", str(work / "l.csv")]}
    check_cli(f"CLI --{name} file", argv[name], capsys)


def test_zz_fuzz_counts(capsys):
    """The tally of this module's run: printed for the closing note, checked in validate."""
    if not COUNTS:
        pytest.skip("no fuzz test ran")
    total = sum(COUNTS.values())
    kinds = ", ".join(f"{k} {v}" for k, v in sorted(COUNTS.items()))
    with capsys.disabled():
        print(f"\nfuzz: {total} malformed inputs ({kinds}); tracebacks "
              f"{sum('traceback' in f for f in FAILURES)}, hangs "
              f"{sum('hang' in f for f in FAILURES)}, wrong successes "
              f"{sum('wrong success' in f for f in FAILURES)}")
    assert not FAILURES, FAILURES[:5]
    if SLOW:
        assert total >= 1000
