"""Fuzz every command of ``robid`` (issue 25): each generated command line has exactly one thing
wrong — a file that is missing, a folder, a FIFO, a device, empty, junk, of another kind or of
an unknown format; an option value out of range or of another mode; a daemon config with one
bad key — and must end in exit 2 with one ``robid: error:`` line naming that file, option or
key. Last: the tally of this module and ``test_fuzz.py`` (``make validate``: ≥ 2000 cases).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import assume, given
from hypothesis import strategies as st

from .conftest import ROBOTS
from .fuzzing import (
    COUNTS,
    FAILURES,
    FUZZ,
    SLOW,
    VERDICTS,
    check_cli,
    check_report,
    is_float,
    json_like,
    not_a_number,
    set_path,
    write,
    yaml_junk,
)

pytestmark = pytest.mark.slow
ARM3 = ROBOTS / "arm3.yaml"


# ----------------------------------------------------------------------------- a valid cell

@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Valid inputs of every kind; each case spoils exactly one of them."""
    work = tmp_path_factory.mktemp("fuzz-cli")
    t = np.arange(400) / 100.0
    q = np.column_stack([np.sin(t * (j + 1)) for j in range(3)])
    cols = np.column_stack([t, q, 0.3 * q + 0.01])
    header = "t,q1,q2,q3,tau1,tau2,tau3"
    np.savetxt(work / "log.csv", cols, delimiter=",", header=header, comments="", fmt="%.6f")
    np.savetxt(work / "traj.csv", np.column_stack([t[:200], q[:200] * 0.1]), delimiter=",",
               header="t,q1,q2,q3", comments="", fmt="%.6f")
    (work / "traj.yaml").write_text("rate_hz: 100\nkind: custom\n")
    (work / "model.yaml").write_text("effects: [rigid_body, viscous, coulomb]\n")
    (work / "truth.yaml").write_text((ROBOTS / "arm3.truth.yaml").read_text())
    (work / "steps.yaml").write_text("rate_hz: 2000\nkind: stepped_sine\nschedule:\n"
                                     "  - {joint: 1, f_hz: 5, t_measure: 1.0, t_end: 2.0}\n")
    (work / "share").mkdir()
    (work / "daemon.yaml").write_text(yaml.safe_dump(_config(work)))
    # a config whose state_dir holds a store (robid web reads it before its address)
    from robid_link.link.store import Store

    Store(work / "stored").close()
    (work / "stored.yaml").write_text(yaml.safe_dump({**_config(work),
                                                      "state_dir": str(work / "stored")}))
    return {"robot": ARM3, "log": work / "log.csv", "traj": work / "traj.csv",
            "model": work / "model.yaml", "truth": work / "truth.yaml",
            "steps": work / "steps.yaml", "share": work / "share",
            "config": work / "daemon.yaml", "stored": work / "stored.yaml",
            "storedir": work / "stored", "work": work}


def _config(work: Path) -> dict[str, Any]:
    return {"robot": str(ARM3), "state_dir": str(work / "state"),
            "control_socket": str(work / "c.sock"),
            "driver": {"name": "file_share", "share": str(work / "share")},
            "campaigns": {"a": {"experiments": ["rigid_body", "friction"],
                                "model": str(work / "model.yaml")}}}


# ----------------------------------------------------------------------------- bad files

#: what a spoiled file is: (category, how it is made from the valid one)
def _missing(work: Path, valid: Path, suffix: str, k: int) -> Path:
    return work / f"missing-{k}{suffix}"


def _folder(work: Path, valid: Path, suffix: str, k: int) -> Path:
    p = work / f"folder{suffix}"
    p.mkdir(exist_ok=True)
    return p


def _fifo(work: Path, valid: Path, suffix: str, k: int) -> Path:
    p = work / f"fifo{suffix}"
    if not p.exists():
        os.mkfifo(p)
    return p


def _device(work: Path, valid: Path, suffix: str, k: int) -> Path:
    return Path(os.devnull)


def _empty(work: Path, valid: Path, suffix: str, k: int) -> Path:
    return write(work / f"empty{suffix}", b"")


def _junk(work: Path, valid: Path, suffix: str, k: int) -> Path:
    rng = np.random.default_rng(k)
    return write(work / f"junk{suffix}", rng.bytes(int(rng.integers(1, 400))))


def _cut(work: Path, valid: Path, suffix: str, k: int) -> Path:
    data = valid.read_bytes()
    return write(work / f"cut{suffix}", data[: k % max(len(data) // 3, 1)] + b"\x00\xff[{")


def _other_kind(work: Path, valid: Path, suffix: str, k: int) -> Path:
    """A valid file of another kind under this one's suffix (a truth file as a robot…)."""
    cell = work.parent
    others = [ARM3, ROBOTS / "arm3.truth.yaml", cell / "model.yaml", cell / "daemon.yaml",
              cell / "traj.csv", cell / "steps.yaml", cell / "log.csv"]
    pick = [o for o in others if o.suffix == suffix and o.resolve() != valid.resolve()]
    source = pick[k % len(pick)] if pick else others[k % len(others)]
    return write(work / f"other-{k % 7}{suffix}", source.read_bytes())


def _suffix(work: Path, valid: Path, suffix: str, k: int) -> Path:
    return write(work / f"valid{['.txt', '.xml', '.json', '.bin', ''][k % 5]}",
                 valid.read_bytes())


SPOILERS: dict[str, Callable[[Path, Path, str, int], Path]] = {
    "missing": _missing, "folder": _folder, "fifo": _fifo, "device": _device, "empty": _empty,
    "junk": _junk, "cut": _cut, "other kind": _other_kind, "suffix": _suffix}

#: command → its valid command line ({slot} for a file of the cell) and the slots to spoil;
#: a slot's spoilers leave out what is not wrong there (a missing --model is created; YAML is
#: YAML under any suffix)
_YAML = ("suffix",)
_CREATED = ("missing", "suffix")
COMMANDS: dict[str, tuple[list[str], dict[str, tuple[str, ...]]]] = {
    "identify": (["identify", "--robot", "{robot}", "--data", "{log}", "--model", "{model}",
                  "--validate", "{log}"], {"robot": (), "log": (), "model": _CREATED}),
    "diagnose": (["diagnose", "--robot", "{robot}", "--data", "{log}", "--model", "{model}"],
                 {"robot": (), "log": (), "model": _CREATED}),
    "history": (["history", "{model}"], {"model": ("suffix",)}),
    "elasticity": (["elasticity", "--robot", "{robot}", "--data", "{log}", "--schedule",
                    "{steps}"], {"robot": (), "log": (), "steps": ("cut", "other kind",
                                                                   "suffix")}),
    "show-robot": (["show-robot", "--robot", "{robot}", "--out", "{work}/r.png"],
                   {"robot": ()}),
    "excite": (["excite", "--robot", "{robot}", "--model", "{model}", "--out",
                "{work}/t.csv"], {"robot": (), "model": _YAML}),
    "simulate": (["simulate", "--robot", "{robot}", "--truth", "{truth}", "--trajectory",
                  "{traj}", "--out", "{work}/sim.csv"],
                 {"robot": (), "truth": _YAML, "traj": ("other kind",)}),
    "fake-controller": (["fake-controller", "--share", "{share}", "--robot", "{robot}",
                         "--truth", "{truth}"], {"robot": (), "truth": _YAML}),
    "config check": (["config", "check", "--config", "{config}"], {"config": _YAML}),
    "daemon": (["daemon", "--config", "{config}"], {"config": _YAML}),
    "campaign start": (["campaign", "start", "a", "--config", "{config}"], {"config": _YAML}),
    "campaign list": (["campaign", "list", "--config", "{config}"], {"config": _YAML}),
    "status": (["status", "--config", "{config}"], {"config": _YAML}),
    "results": (["results", "--config", "{config}"], {"config": _YAML}),
    "params": (["params", "show", "--config", "{config}", "--robot", "arm3"],
               {"config": _YAML}),
    "web": (["web", "--config", "{config}"], {"config": _YAML}),
    # a valid model would reach the (empty) store: another kind of YAML may be a model
    "fleet reidentify": (["fleet", "reidentify", "--store", "{storedir}", "--model", "{model}"],
                         {"model": ("suffix", "other kind")}),
}


def file_case() -> st.SearchStrategy[tuple[str, str, str, int]]:
    """(command, slot, spoiler, seed) of every command's every file slot."""
    cases = [(c, slot, s) for c, (_, slots) in COMMANDS.items() for slot, skip in slots.items()
             for s in SPOILERS if s not in skip]
    return st.tuples(st.sampled_from(cases), st.integers(0, 10_000)).map(
        lambda m: (*m[0], m[1]))


def _argv(template: list[str], cell: dict[str, Path], spoilt: str = "", bad: str = ""
          ) -> list[str]:
    out = []
    for a in template:
        for key, value in cell.items():
            a = a.replace(f"{{{key}}}", bad if key == spoilt else str(value))
        out.append(a)
    return out


@FUZZ
@given(case=file_case())
def test_fuzz_cli_files(cell, capsys, case):
    command, slot, spoiler, k = case
    template, _ = COMMANDS[command]
    valid = cell[slot]
    folder = cell["work"] / slot  # one folder per slot: a spoilt header is not another's
    folder.mkdir(exist_ok=True)
    bad = SPOILERS[spoiler](folder, valid, valid.suffix, k)
    # a trajectory is two files (CSV and its .yaml header): the message names either
    name = bad.with_suffix("") if slot == "traj" and bad.suffix == ".csv" else bad
    check_cli(f"CLI {command}", _argv(template, cell, slot, str(bad)), capsys, name)


@FUZZ
@given(name=st.sampled_from(["robot", "model", "truth", "trajectory"]), text=yaml_junk())
def test_fuzz_cli_yaml_files(cell, capsys, name, text):
    """YAML junk as each YAML input of the commands."""
    work = cell["work"]
    p = write(work / f"cli-{name}.yaml", text)
    if name == "trajectory":
        write(work / "cli-trajectory.csv", "t,q1,q2,q3\n0,0,0,0\n0.01,0,0,0\n")
    argv = {"robot": ["show-robot", "--robot", p, "--out", work / "r.png"],
            "model": ["excite", "--robot", ARM3, "--model", p, "--out", work / "t.csv"],
            "truth": ["simulate", "--robot", ARM3, "--truth", p, "--trajectory", cell["traj"],
                      "--out", work / "l.csv"],
            "trajectory": ["simulate", "--robot", ARM3, "--truth", cell["truth"],
                           "--trajectory", work / "cli-trajectory.csv", "--out",
                           work / "l.csv"]}
    check_cli(f"CLI --{name} YAML", argv[name], capsys, p)


# ----------------------------------------------------------------------------- bad options

_IDENTIFY = ["identify", "--robot", "{robot}", "--data", "{log}"]
_EXCITE = ["excite", "--robot", "{robot}", "--out", "{work}/t.csv"]
_ELASTIC = [*_EXCITE, "--kind", "elasticity"]
_RESULTS = ["results", "--config", "{config}", "--robot", "arm3", "--trend"]
#: option → (the command line before it, its kind of value)
OPTIONS: dict[str, tuple[list[str], str]] = {
    "--cutoff": (_IDENTIFY, "float"),
    "--fs": (["diagnose", "--robot", "{robot}", "--data", "x.mat"], "rate"),
    "--interval": (_IDENTIFY, "int"),
    "--method": (_IDENTIFY, "word"),
    "--weight": ([*_IDENTIFY, "--method", "irls"], "word"),
    "--add": (_IDENTIFY, "effect"),
    "--lock": (_IDENTIFY, "word"),
    "--topic": (_IDENTIFY, "word"),
    "--rate": (_EXCITE, "rate"),
    "--duration": (_EXCITE, "float"),
    "--base-hz": (_EXCITE, "float"),
    "--harmonics": (_EXCITE, "int"),
    "--evaluations": (_EXCITE, "int"),
    "--kind": (_EXCITE, "word"),
    "--f-min": (_ELASTIC, "float"),
    "--f-max": (_ELASTIC, "float"),
    "--steps": (_ELASTIC, "int"),
    "--pair": (_ELASTIC, "pair"),
    "--joint": (["elasticity", "--robot", "{robot}", "--data", "{log}"], "int"),
    "--joints": (["elasticity", "--robot", "{robot}", "--data", "{log}"], "pair"),
    "--seed": (["simulate", "--robot", "{robot}", "--truth", "{truth}", "--trajectory",
                "{traj}", "--out", "{work}/l.csv"], "int"),
    "--fault-count": (["fake-controller", "--share", "{share}", "--robot", "{robot}",
                       "--fault", "die"], "int"),
    "--fault": (["fake-controller", "--share", "{share}", "--robot", "{robot}"], "word"),
    "--driver": (["fake-controller", "--share", "{share}", "--robot", "{robot}"], "word"),
    "--option": (["fake-controller", "--share", "{share}", "--robot", "{robot}"], "keyvalue"),
    "--q": (["show-robot", "--robot", "{robot}", "--out", "{work}/x.png"], "floats"),
    "--pose": (_ELASTIC, "floats"),
    "--sigma": (_RESULTS, "float"),
    "--min-change": (_RESULTS, "float"),
    "--trigger": (["campaign", "start", "a", "--config", "{config}"], "word"),
    "--listen": (["web", "--config", "{stored}"], "word"),
}


def _values(kind: str) -> st.SearchStrategy[str]:
    bad_float = st.one_of(st.sampled_from(["nan", "inf", "-inf", "1e999", "-1", "0", "", "x",
                                           "1e10", "0x1p3", "1/2"]),
                          st.floats(max_value=-1e-9).map(repr),
                          st.text(max_size=6).filter(lambda s: not is_float(s)))
    bad_int = st.one_of(st.sampled_from(["1.5", "1e3", "-1", "9" * 30, "nan", "inf", "", "x",
                                         "0x10", " ", "1_0", "٣"]),
                        st.integers(10 ** 20, 10 ** 40).map(str),
                        st.text(max_size=6).filter(lambda s: not s.strip().isdigit()))
    word = st.one_of(st.sampled_from(["nope", "", "OLS", "-", "x" * 80, "../etc"]),
                     st.text(alphabet="abcxyz_/@", min_size=1, max_size=8).filter(
                         lambda s: s not in ("abc",)))
    return {"float": bad_float, "int": bad_int, "word": word,
            "rate": st.one_of(bad_float, st.sampled_from(["1e-6", "0.5", "9.9", "1e7"])),
            "effect": st.sampled_from(["warp", "viscous@9", "viscous@0", "viscous@", "@1",
                                       "ripple@1:x", "coulomb@m9", "rigid_body@1"]),
            "pair": st.sampled_from(["1", "1,", "a,b", "1,2,3", "0,9", "1,1", "", "9,10"]),
            "keyvalue": st.sampled_from(["x", "=1", "port", "1x=2", "port=[", "nope=1"]),
            "floats": st.sampled_from(["nan", "inf", "x", "1e999"]),
            }[kind]


def option_case(commands: tuple[str, ...]) -> st.SearchStrategy[tuple[str, str]]:
    """(option, bad value) over the options of ``commands``."""
    return st.sampled_from(sorted(o for o, (before, _) in OPTIONS.items()
                                  if before[0] in commands)).flatmap(
        lambda o: _values(OPTIONS[o][1]).map(lambda v: (o, v)))


@FUZZ
@given(case=option_case(("identify", "diagnose", "elasticity")))
def test_fuzz_cli_analysis_options(cell, capsys, case):
    _option(cell, capsys, case)


@FUZZ
@given(case=option_case(("excite", "simulate", "show-robot")))
def test_fuzz_cli_robot_options(cell, capsys, case):
    _option(cell, capsys, case)


@FUZZ
@given(case=option_case(("fake-controller", "results", "campaign", "web")))
def test_fuzz_cli_operator_options(cell, capsys, case):
    _option(cell, capsys, case)


def _option(cell: dict[str, Path], capsys: pytest.CaptureFixture[str], case: tuple[str, str]
            ) -> None:
    option, value = case
    before, kind = OPTIONS[option]
    if (option, value) in (("--weight", "andrews"), ("--weight", "bisquare"), ("--fault", ""),
                           ("--listen", "")):
        return  # a valid choice; nothing given (the fake controller or the page would serve)
    # nargs="+" (--q, --pose): a bad value among good ones, else a count the robot has not
    extra = ["0", value] if kind == "floats" else [value]
    # the page's address is web.listen in the config, --listen on the command line
    name = "listen" if option == "--listen" else option
    check_cli(f"CLI {option}", [*_argv(before, cell), option, *extra], capsys, name)


#: options that another option or the chosen mode makes meaningless: (argv, option named)
CONTRADICTIONS: list[tuple[list[str], str]] = [
    ([*_IDENTIFY, "--weight", "huber"], "--weight"),
    ([*_IDENTIFY, "--method", "wls", "--weight", "cauchy"], "--weight"),
    ([*_IDENTIFY, "--export-urdf", "{work}/x.urdf"], "--export-urdf"),
    ([*_IDENTIFY, "--fs", "500"], "--fs"),
    ([*_IDENTIFY, "--topic", "/joint_states"], "--topic"),
    ([*_IDENTIFY, "--lock", "j1"], "--lock"),
    ([*_EXCITE, "--steps", "6"], "--steps"),
    ([*_EXCITE, "--pose", "0", "0", "0"], "--pose"),
    ([*_EXCITE, "--f-max", "30"], "--f-max"),
    ([*_EXCITE, "--joint", "1"], "--joint"),
    ([*_ELASTIC, "--harmonics", "4"], "--harmonics"),
    ([*_ELASTIC, "--evaluations", "10"], "--evaluations"),
    ([*_ELASTIC, "--model", "{model}"], "--model"),
    ([*_ELASTIC, "--seed", "2"], "--seed"),
    (["results", "--config", "{config}", "--sigma", "3"], "--sigma"),
    (["results", "--config", "{config}", "--out", "{work}/t.png"], "--out"),
    (["results", "--config", "{config}", "--compare", "a", "b", "--robot", "c"], "--robot"),
    (["results", "--config", "{config}", "--trend"], "--trend"),
    (["params", "diff", "1", "--config", "{config}", "--robot", "r"], "params diff"),
    (["params", "rollback", "2", "--config", "{config}", "--robot", "r"], "params rollback"),
    (["params", "approve", "--json", "{work}/p.json", "--config", "{config}", "--robot", "r"],
     "--json"),
    (["fake-controller", "--share", "{share}", "--robot", "{robot}", "--fault-count", "3"],
     "--fault-count"),
    (["demo", "--driver", "nope", "--out", "{work}/demo"], "--driver nope"),
    (["show-robot", "--robot", "{robot}", "--out", "{work}/x.xyz"], "x.xyz"),
    (["show-robot", "--robot", "{robot}", "--out", "/proc/robid/x.png"], "/proc/robid/x.png"),
    ([*_IDENTIFY, "--json", os.devnull], os.devnull),
    ([*_IDENTIFY, "--out", "{log}"], "--out"),
]


@FUZZ
@given(k=st.integers(0, len(CONTRADICTIONS) - 1))
def test_fuzz_cli_contradictions(cell, capsys, k):
    argv, name = CONTRADICTIONS[k]
    check_cli("CLI contradiction", _argv(argv, cell), capsys, name)


# ----------------------------------------------------------------------------- config keys

def config_key_case() -> st.SearchStrategy[tuple[tuple[Any, ...], Any, str]]:
    """(key path, bad value, the key path the message names) over every key of the config,
    of its campaigns and of each experiment kind's options."""
    from robid_link.kinds import KIND_OPTIONS

    top = [(("robot",), "robot"), (("state_dir",), "state_dir"),
           (("control_socket",), "control_socket"), (("driver",), "driver"),
           (("campaigns",), "campaigns"), (("lock",), "lock"), (("socket_mode",), "socket_mode"),
           (("worker_start_method",), "worker_start_method"), (("log_level",), "log_level"),
           (("web",), "web"), (("store",), "store"), (("robot_name",), "robot_name"),
           (("log_store",), "log_store")]
    camp = [(("campaigns", "a", k), f"campaigns.a.{k}") for k in (
        "experiments", "identify", "diagnose", "model", "add", "method", "retries",
        "backoff_s", "timeout_s", "reduced_speed_first", "cutoff_hz", "motor_side", "upload")]
    exp = [(kind, key) for kind, spec in KIND_OPTIONS.items() for key in spec.defaults]
    bad = st.one_of(json_like.filter(lambda v: v is not None), not_a_number.filter(
        lambda v: v is not None), st.sampled_from([-1, 0, 1e12, "x", [], {}, True]))
    plain = st.tuples(st.sampled_from(top + camp), bad).map(lambda m: (m[0][0], m[1],
                                                                       m[0][1]))
    options = st.tuples(st.sampled_from(exp), bad).map(
        lambda m: (("campaigns", "a", "experiments", 0), {"kind": m[0][0], m[0][1]: m[1]},
                   f"campaigns.a.experiments[0].{m[0][1]}"))
    return st.one_of(plain, options)


def _spoils(doc: dict[str, Any], path: tuple[Any, ...], value: Any) -> bool:
    """Whether ``value`` at ``path`` makes the config fail to load (some values are fine)."""
    import tempfile

    from robid_link.config import load_daemon_config
    from robid_link.exceptions import RobidError

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "d.yaml"
        p.write_text(yaml.safe_dump(set_path(doc, path, value)))
        try:
            load_daemon_config(p)
        except RobidError:
            return True
    return False


@FUZZ
@given(case=config_key_case(), command=st.sampled_from(["config check", "daemon", "status",
                                                        "results", "campaign list"]))
def test_fuzz_cli_config_keys(cell, capsys, case, command):
    path, value, key = case
    doc = _config(cell["work"])
    try:
        text = yaml.safe_dump(set_path(doc, path, value))
    except yaml.YAMLError:
        text = ""
    assume(text and _spoils(doc, path, value))  # some values are valid there
    p = write(cell["work"] / "bad-daemon.yaml", text)
    template, _ = COMMANDS[command]
    check_cli(f"CLI config {key.split('.')[0]}", _argv(template, {**cell, "config": p}),
              capsys, key)


# ----------------------------------------------------------------------------- drivers

def _driver_bases(cell: dict[str, Path]) -> dict[str, dict[str, Any]]:
    """A valid ``driver:`` mapping of each built-in driver (its required options)."""
    work = cell["work"]
    creds = work / "rws.credentials"
    if not creds.exists():
        creds.write_text("user: a\npassword: b\n")
        creds.chmod(0o600)
    eds = write(work / "drives.eds", "[FileInfo]\n")
    share = str(cell["share"])
    return {"file_share": {"share": share},
            "modbus_plc": {"host": "127.0.0.1", "share": share},
            "serial_line": {"port": "/dev/ttyUSB0"},
            "abb_rws": {"version": 2, "url": "https://127.0.0.1:1",
                        "credentials_file": str(creds)},
            "canopen_drives": {"nodes": [1, 2, 3], "counts_per_rad": [1000, 1000, 1000],
                               "eds": str(eds)},
            "ur_rtde": {"host": "127.0.0.1"}}


def test_every_built_in_driver_has_a_valid_base(cell):
    """The driver fuzz spoils one option of a valid mapping: a new driver needs its own."""
    from robid_link.link.registry import BUILTIN_DRIVERS, make_driver

    bases = _driver_bases(cell)
    assert set(bases) == set(BUILTIN_DRIVERS)
    for name, options in bases.items():
        make_driver({"name": name, **options})


def driver_case() -> st.SearchStrategy[tuple[str, str, Any]]:
    """(driver, option, bad value) over every option of every built-in driver."""
    from robid_link.link.registry import BUILTIN_DRIVERS, driver_class

    keys = [(d, k) for d in sorted(BUILTIN_DRIVERS) for k in driver_class(d).options]
    bad = st.one_of(json_like, not_a_number, st.sampled_from(
        [-1, 0, 1e12, "", "x", [], {}, True, "/proc/none", 70_000, [0], [1, 1, 1]]))
    return st.tuples(st.sampled_from(keys), bad).map(lambda m: (*m[0], m[1]))


def _driver_refuses(options: dict[str, Any]) -> bool:
    from robid_link.exceptions import RobidError
    from robid_link.link.registry import make_driver

    try:
        make_driver(options)
    except RobidError:
        return True
    return False


@FUZZ
@given(case=driver_case())
def test_fuzz_cli_driver_options(cell, capsys, case):
    """A driver option of the wrong type or range (the TypeError of issue 25 among them):
    config check and the daemon refuse it in one line naming ``driver.<key>``."""
    driver, key, value = case
    options = {"name": driver, **_driver_bases(cell)[driver], key: value}
    try:
        text = yaml.safe_dump({**_config(cell["work"]), "driver": options})
    except yaml.YAMLError:
        text = ""
    assume(text and _driver_refuses(options))
    p = write(cell["work"] / "bad-driver.yaml", text)
    check_cli(f"CLI driver {driver}", ["config", "check", "--config", p], capsys, f"driver.{key}")


# ----------------------------------------------------------------------------- config paths

def _quick_config(cell: dict[str, Path]) -> dict[str, Any]:
    """A config whose check is quick: one campaign of a custom trajectory and a model."""
    return {**_config(cell["work"]), "campaigns": {"a": {
        "experiments": [{"kind": "custom", "id": "path", "trajectory": str(cell["traj"])}],
        "model": str(cell["model"])}}}


PATH_KEYS = {  # key → (its place in the config, what it must be)
    "robot": (("robot",), "file"), "state_dir": (("state_dir",), "folder"),
    "control_socket": (("control_socket",), "socket"), "driver.share": (("driver", "share"),
                                                                       "folder"),
    "log_store": (("log_store",), "folder"),
    "campaigns.a.model": (("campaigns", "a", "model"), "file"),
    "campaigns.a.experiments.path.trajectory": (
        ("campaigns", "a", "experiments", 0, "trajectory"), "file")}


def _bad_path(work: Path, want: str, how: str, k: int) -> Path:
    folder = work / "paths"
    folder.mkdir(exist_ok=True)
    if how == "missing":
        return folder / f"missing-{k}" / "x.yaml" if k % 2 else folder / f"missing-{k}.yaml"
    if how == "fifo":
        return _fifo(folder, folder, ".yaml", k)
    if how == "device":
        return Path(os.devnull)
    if how == "folder":
        return _folder(folder, folder, ".yaml", k)
    if how == "file":
        return write(folder / "a-file", "x")
    if how == "below a file":
        return write(folder / "a-file", "x") / "x"
    return Path("/proc/robid/x")  # cannot be made, not even by root


@FUZZ
@given(key=st.sampled_from(sorted(PATH_KEYS)), how=st.sampled_from(
    ["missing", "fifo", "device", "folder", "file", "below a file", "/proc"]),
    k=st.integers(0, 1000))
def test_fuzz_cli_config_paths(cell, capsys, key, how, k):
    """Every path of the config, spoilt: config check says which key, which path, what."""
    place, want = PATH_KEYS[key]
    # what it must be is no spoiling; a missing state_dir or socket (and folder) is made
    assume((want, how) not in (("file", "file"), ("folder", "folder"), ("socket", "folder"))
           and not (key in ("state_dir", "control_socket", "log_store") and how == "missing"))
    bad = _bad_path(cell["work"], want, how, k)
    doc = set_path(_quick_config(cell), place, str(bad))
    p = write(cell["work"] / "paths.yaml", yaml.safe_dump(doc))
    check_report(f"CLI config check {key}", ["config", "check", "--config", p], capsys, bad)


# ----------------------------------------------------------------------------- plant stores

#: --store commands: a plant's store or a daemon's state dir, read (and written by reidentify)
STORE_COMMANDS = {
    "status": ["status", "--store", "{store}"],
    "results": ["results", "--store", "{store}", "--robot", "arm3"],
    "results --trend": ["results", "--store", "{store}", "--robot", "arm3", "--trend"],
    "fleet": ["fleet", "--store", "{store}", "--workers", "1"],
    "fleet reidentify": ["fleet", "reidentify", "--store", "{store}", "--model", "{model}"],
}
#: what is given as --store: a spoilt state dir (named by its path) or a bad URL (--store)
STORE_SPOILERS = ("missing", "a file", "fifo", "device", "empty folder", "junk database",
                  "empty database", "a folder as database", "")
STORE_URLS = ("sqlite:///x.db", "http://db/robid", "postgresql://robid:hunter2@db/robid",
              "postgresql://db", "postgresql://robid@db:99999/robid", "postgres:", " ")


def _bad_store(work: Path, how: str, k: int) -> Path:
    folder = work / "stores" / f"{how.replace(' ', '-')}-{k}"
    folder.parent.mkdir(exist_ok=True)
    if how == "missing":
        return folder
    if how in ("a file", "fifo", "device"):
        return {"a file": lambda: write(folder, "robid"), "device": lambda: Path(os.devnull),
                "fifo": lambda: _fifo(folder.parent, folder, "", k)}[how]()
    folder.mkdir(exist_ok=True)
    db = folder / "robid.sqlite"
    if how == "junk database":
        write(db, np.random.default_rng(k).bytes(1 + k % 3000))
    elif how == "empty database":
        write(db, b"")
    elif how == "a folder as database":
        db.mkdir(exist_ok=True)
    return folder


@FUZZ
@given(command=st.sampled_from(sorted(STORE_COMMANDS)), how=st.one_of(
    st.sampled_from(STORE_SPOILERS[:-1]), st.sampled_from(STORE_URLS)), k=st.integers(0, 999))
def test_fuzz_cli_stores(cell, capsys, command, how, k):
    """``robid status/results/fleet --store``: a state dir that is not one, a damaged store,
    a URL robid does not take."""
    if how in STORE_SPOILERS:
        bad: Path | str = _bad_store(cell["work"], how, k)
        name: Path | str = bad
    else:
        bad, name = how, "--store"
    check_cli(f"CLI {command} --store", _argv(STORE_COMMANDS[command], {**cell, "store": bad}),
              capsys, name)


# ----------------------------------------------------------------------------- bags

@FUZZ
@given(kind=st.sampled_from(("sqlite3", "mcap", "mcap-file", "ros1")),
       mutation=st.sampled_from(("drop_joint", "no_effort", "nan", "backwards", "few",
                                 "other_type", "two_topics", "truncate", "empty", "topic")),
       command=st.sampled_from(("identify", "diagnose", "elasticity")), k=st.integers(0, 999))
def test_fuzz_cli_bags(cell, capsys, kind, mutation, command, k):
    """ROS recordings through the commands that read logs (a bag folder, .mcap, .bag)."""
    import shutil

    from .test_fuzz import _write_bag

    folder = cell["work"] / "bags"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    bag = _write_bag(folder, kind, "none" if mutation == "topic" else mutation, k, k)
    argv = [command, "--robot", ARM3, "--data", bag]
    name: Path | str = bag
    if mutation == "topic":  # a sound recording, a topic it does not hold
        argv += ["--topic", f"/arm{k}/joint_states"]
        name = f"/arm{k}/joint_states"
    check_cli(f"CLI bag ({kind})", argv, capsys, name)


# ----------------------------------------------------------------------------- the tally

def test_zz_fuzz_counts(record_property):
    """The tally of the fuzz modules' run: printed at the end of the run for the closing note
    (tests/conftest.py), checked in validate."""
    if not COUNTS:
        pytest.skip("no fuzz test ran")
    total = sum(COUNTS.values())
    kinds = ", ".join(f"{k} {v}" for k, v in sorted(COUNTS.items()))
    plural = {"traceback": "tracebacks", "hang": "hangs", "unnamed error": "unnamed errors",
              "wrong success": "wrong successes"}
    verdicts = ", ".join(f"{plural[v]} {sum(f[0] == v for f in FAILURES)}" for v in VERDICTS)
    first = {text.split(":")[0]: (verdict, text) for verdict, text in reversed(FAILURES)}
    record_property("summary", f"fuzz: {total} malformed inputs ({kinds}); {verdicts}")
    for verdict, text in first.values():  # the first of each kind (shrinking repeats it)
        record_property("summary", f"  {verdict}: {text}")
    assert not FAILURES, list(first.values())[:5]
    if SLOW and "log CSV" in COUNTS:  # the whole fuzz ran (both modules)
        assert total >= 2000, total
