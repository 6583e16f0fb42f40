"""The door between the link and the worker: the typed, versioned job and result records, and
what both sides check alike (experiment ids as file names, parameter sets; kinds' options:
kinds.py). The wire format (``Record``, JSON both ways, one-line errors) is ``records.py``,
re-exported here. The worker's entry point is named here (``WORKER_ENTRY``) and imported by
name in the child: this module imports nothing numerical (numpy only inside
``MotionProgram.trajectory``).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

from robid_link.exceptions import DriverError, ModelError
from robid_link.records import RECORDS, SCHEMA, Job, Record

if TYPE_CHECKING:
    import numpy as np

__all__ = [
    "SCHEMA", "WORKER_ENTRY", "WORKER_PRELOAD", "RECORDS", "Record", "Job",
    "check_name",
    "PARAMETER_SET_FORMAT", "canonical_bytes", "set_sha256",
    "RobotInfo", "MotionProgram", "ProgramTrajectory", "ParameterSet", "ResonanceHint",
    "RobotInfoJob", "ProgramJob", "LogCheckJob", "LogCheck", "ModelCheckJob", "ModelCheck",
    "IdentifyJob", "IdentifyOutcome", "VerifyRun", "VerifyJob", "VerifyOutcome",
    "ElasticityRun", "ElasticityJob", "ElasticityOutcome", "FeedforwardJob", "FeedforwardTable",
    "DriftFlag", "DriftJob", "DriftReport",
]

#: the worker process's entry point (``module:function``, JSON job in, JSON result out)
WORKER_ENTRY = "robid_link.ident.entry:run"
#: what a fork server imports once, so each worker forks with the numerical stack loaded
WORKER_PRELOAD = ("robid_link.ident.entry", "robid_link.ident.excite.experiments",
                  "robid_link.ident.fit.identify", "robid_link.ident.diagnosis.diagnose")

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_\-]{0,63}$")


def check_name(value: str, what: str) -> str:
    """Experiment ids and nonces become file names: letters, digits, '_' and '-' only, so no
    name can escape a folder or collide with the protocol's dots."""
    if not isinstance(value, str) or not _NAME.match(value):
        raise DriverError(f"{what} {value!r}: expected 1-64 letters, digits, '_' or '-'")
    return value


# ----------------------------------------------------------------------------- values


@dataclass(frozen=True)
class RobotInfo(Record):
    """What the link and a driver know of the robot (no Pinocchio model): joints in model
    order, their types and limits in SI units (``inf`` where unknown)."""

    TYPE: ClassVar[str] = "robot-info"
    name: str
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    q_min: tuple[float, ...]
    q_max: tuple[float, ...]
    qd_max: tuple[float, ...]
    qdd_max: tuple[float, ...]
    tau_max: tuple[float, ...]

    @property
    def n(self) -> int:
        return len(self.joint_names)

    @classmethod
    def of(cls, robot: Any) -> RobotInfo:
        """From the worker's robot model (read by attribute: nothing is imported here)."""
        lim = robot.limits
        return cls(robot.name, tuple(robot.joint_names), tuple(robot.joint_types),
                   *(tuple(float(x) for x in a)
                     for a in (lim.q_min, lim.q_max, lim.qd_max, lim.qdd_max, lim.tau_max)))


@dataclass(frozen=True)
class ProgramTrajectory:
    """The neutral trajectory of a program, parsed back from its files: what a driver renders
    for its controller (RAPID, counts per SYNC, …). A value, not a record: it never crosses
    the door as such (its MotionProgram does)."""

    t: np.ndarray
    q: np.ndarray
    rate_hz: float
    kind: str
    robot: str
    joint_types: tuple[str, ...]
    header: Mapping[str, Any]


@dataclass(frozen=True)
class MotionProgram(Record):
    """One experiment's program as it leaves the worker: the neutral trajectory (``traj.csv``
    + ``traj.yaml``), already checked against the robot's limits. This is what an operator
    approves by hash; a driver renders it for its controller in ``_put_program``."""

    TYPE: ClassVar[str] = "motion-program"
    exp_id: str
    files: Mapping[str, bytes]
    duration_s: float
    meta: Mapping[str, Any] = field(default_factory=dict)

    @property
    def sha256(self) -> str:
        """Hash of the program's content (what an operator approves)."""
        h = hashlib.sha256()
        for suffix in sorted(self.files):
            h.update(suffix.encode() + b"\0" + self.files[suffix] + b"\0")
        return h.hexdigest()

    def trajectory(self) -> ProgramTrajectory:
        """``traj.csv`` + ``traj.yaml`` parsed; a DriverError names what is wrong."""
        import io

        import numpy as np
        import yaml

        from robid_link.safeyaml import load_yaml

        where = f"program {self.exp_id}"
        try:
            head = load_yaml(self.files["traj.yaml"], f"{where}: traj.yaml", error=DriverError)
            arr = np.loadtxt(io.BytesIO(self.files["traj.csv"]), delimiter=",", skiprows=1,
                             ndmin=2)
        except KeyError as err:
            raise DriverError(f"{where}: file {err.args[0]} missing") from err
        except (ValueError, UnicodeDecodeError, yaml.YAMLError) as err:
            raise DriverError(f"{where}: unreadable trajectory ({err})") from err
        if not isinstance(head, dict) or arr.shape[1] < 2 or arr.shape[0] < 1:
            raise DriverError(f"{where}: trajectory header or samples malformed")
        n = arr.shape[1] - 1
        types_ = tuple(head.get("joint_types") or ("revolute",) * n)
        if len(types_) != n or not np.all(np.isfinite(arr)):
            raise DriverError(f"{where}: {n} joints in traj.csv, {len(types_)} joint types in "
                              "traj.yaml, or non-finite samples")
        try:
            rate = float(head["rate_hz"])
        except (KeyError, TypeError, ValueError) as err:
            raise DriverError(f"{where}: traj.yaml has no valid rate_hz") from err
        return ProgramTrajectory(arr[:, 0], arr[:, 1:], rate, str(head.get("kind", "custom")),
                                 str(head.get("robot", "")), types_, head)


#: the parameter set's format name and version (a controller refuses what it does not know)
PARAMETER_SET_FORMAT = "robid-parameter-set/1"


def canonical_bytes(doc: Mapping[str, Any]) -> bytes:
    """A parameter set's bytes as hashed: sorted keys, no NaN, one line, without its sha256."""
    body = {k: v for k, v in doc.items() if k != "sha256"}
    return (json.dumps(body, sort_keys=True, allow_nan=False, separators=(",", ":"))
            + "\n").encode()


def set_sha256(doc: Mapping[str, Any]) -> str:
    return hashlib.sha256(canonical_bytes(doc)).hexdigest()


def _numbers(value: Any, size: int) -> bool:
    return (isinstance(value, list) and len(value) == size
            and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value))


@dataclass(frozen=True)
class ParameterSet(Record):
    """A ``robid-parameter-set/1`` document (what the identification hands a controller), as
    data: ``from_doc`` checks its format and hash, ``check`` its sizes against a robot."""

    TYPE: ClassVar[str] = "parameter-set"
    doc: Mapping[str, Any]

    @property
    def sha256(self) -> str:
        return str(self.doc.get("sha256"))

    @property
    def robot(self) -> str | None:
        name = self.doc.get("robot")
        return None if name is None else str(name)

    @classmethod
    def from_doc(cls, doc: Any) -> ParameterSet:
        """The set, or ModelError: not a set of this format, or damaged (hash)."""
        if not isinstance(doc, Mapping):
            raise ModelError("parameter set: expected a JSON object")
        name = _set_name(doc)
        if doc.get("format") != PARAMETER_SET_FORMAT:
            raise ModelError(f"{name}: format {doc.get('format')!r}, expected "
                             f"{PARAMETER_SET_FORMAT}")
        try:
            sha = set_sha256(doc)
        except (TypeError, ValueError) as err:
            raise ModelError(f"{name}: not canonical JSON ({err})") from err
        if doc.get("sha256") != sha:
            # short: a controller's refusal quotes it in an 80-character RAPID string
            raise ModelError(f"{name}: damaged (sha256 mismatch)")
        return cls(dict(doc))

    def check(self, n_joints: int) -> None:
        """What a controller needs of the set for an ``n_joints`` robot; ModelError names the
        problem."""
        name = _set_name(self.doc)
        fr = self.doc.get("friction") or {}
        lists = [fr.get(k, [0.0] * n_joints) if isinstance(fr, Mapping) else None
                 for k in ("viscous", "coulomb", "offset")]
        inert = self.doc.get("standard_inertials")
        if not all(_numbers(v, n_joints) for v in lists) or (
                inert is not None and not _numbers(inert, 10 * n_joints)):
            raise ModelError(f"{name}: sizes do not fit a {n_joints}-joint robot")
        if inert is not None and not all(math.isfinite(x) for x in inert):
            raise ModelError(f"{name}: standard inertials hold a non-finite number")
        if not all(math.isfinite(x) for v in lists for x in v or ()):
            raise ModelError(f"{name}: friction holds a non-finite number")
        for r in self.doc.get("ripple") or []:
            ok = isinstance(r, Mapping) and all(
                isinstance(r.get(k), int | float) and not isinstance(r.get(k), bool)
                for k in ("joint", "period", "sin", "cos"))
            if not ok:
                raise ModelError(f"{name}: a ripple entry lacks a number of joint, period, "
                                 "sin or cos")
            if not 1 <= r["joint"] <= n_joints or not r["period"] > 0:
                raise ModelError(f"{name}: ripple of joint {r['joint']} (period "
                                 f"{r['period']}) does not fit a {n_joints}-joint robot")


def _set_name(doc: Mapping[str, Any]) -> str:
    """A parameter set as errors name it: by the hash it claims."""
    sha = doc.get("sha256")
    return f"parameter set {sha[:12]}" if isinstance(sha, str) and sha else "parameter set"


@dataclass(frozen=True)
class ResonanceHint(Record):
    """What the diagnosis tells the user about an unexplained resonance on ``joint``: the
    experiment that measures its elasticity (``measured_by``), and the advice (``todo``)."""

    TYPE: ClassVar[str] = "resonance-hint"
    joint: int
    measured_by: str | None
    todo: str


# ----------------------------------------------------------------------------- jobs


@dataclass(frozen=True)
class RobotInfoJob(Job):
    """Load the robot description (``lock``: URDF joints held fixed) → RobotInfo."""

    TYPE: ClassVar[str] = "robot-info-job"
    RESULT: ClassVar[type[Record]] = RobotInfo
    robot: str
    lock: tuple[str, ...]


@dataclass(frozen=True)
class ProgramJob(Job):
    """Generate, limit-check and package one experiment's program → MotionProgram."""

    TYPE: ClassVar[str] = "program-job"
    RESULT: ClassVar[type[Record]] = MotionProgram
    robot: str
    lock: tuple[str, ...]
    exp_id: str
    kind: str
    options: Mapping[str, Any]
    base_dir: str
    reduced_speed: float | None
    #: joints (from 1) whose torque the controller is to log (a campaign's ``channels``
    #: budget): written into the program's ``traj.yaml`` as ``log_torques``; None: every joint
    log_torques: tuple[int, ...] | None = None


@dataclass(frozen=True)
class LogCheck(Record):
    TYPE: ClassVar[str] = "log-check"
    samples: int
    duration_s: float
    rate_hz: float


@dataclass(frozen=True)
class LogCheckJob(Job):
    """Load a captured log as the identification will (columns, joints, NaN, time)."""

    TYPE: ClassVar[str] = "log-check-job"
    RESULT: ClassVar[type[Record]] = LogCheck
    log: str
    n_joints: int


@dataclass(frozen=True)
class ModelCheck(Record):
    TYPE: ClassVar[str] = "model-check"
    effects: tuple[str, ...]


@dataclass(frozen=True)
class ModelCheckJob(Job):
    """Build the model a run's identification will use (file, ``add:`` entries) now."""

    TYPE: ClassVar[str] = "model-check-job"
    RESULT: ClassVar[type[Record]] = ModelCheck
    model: str | None
    add: tuple[str, ...]


@dataclass(frozen=True)
class IdentifyOutcome(Record):
    """Records by kind (``identify``, ``diagnose``), the summary text, and the parameter set
    (a consistent fit when the run uploads)."""

    TYPE: ClassVar[str] = "identify-outcome"
    robot: str
    records: Mapping[str, Any]
    summary: str
    parameter_set: ParameterSet


@dataclass(frozen=True)
class IdentifyJob(Job):
    """Identify (and diagnose) a run's logs and write its report into ``report_dir``."""

    TYPE: ClassVar[str] = "identify-job"
    RESULT: ClassVar[type[Record]] = IdentifyOutcome
    run_id: str
    robot: str
    lock: tuple[str, ...]
    logs: tuple[str, ...]
    report_dir: str
    model: str | None
    add: tuple[str, ...]
    method: str
    diagnose: bool
    cutoff_hz: float | None
    motor_side: bool
    upload: bool
    resonance_hints: tuple[ResonanceHint, ...]
    #: the daemon campaign whose run this is (named in the report)
    campaign: str | None = None


@dataclass(frozen=True)
class VerifyRun(Record):
    TYPE: ClassVar[str] = "verify-run"
    exp_id: str
    phase: str
    log: str
    program: MotionProgram


@dataclass(frozen=True)
class VerifyOutcome(Record):
    TYPE: ClassVar[str] = "verify-outcome"
    robot: str
    records: tuple[Mapping[str, Any], ...]


@dataclass(frozen=True)
class VerifyJob(Job):
    """Tracking of each verification log against the path its program gave."""

    TYPE: ClassVar[str] = "verify-job"
    RESULT: ClassVar[type[Record]] = VerifyOutcome
    robot: str
    lock: tuple[str, ...]
    runs: tuple[VerifyRun, ...]
    #: the run's report folder: its report.html gains the tracking section (None: no report)
    report_dir: str | None = None
    #: the daemon run and campaign the report names
    run_id: str | None = None
    campaign: str | None = None


@dataclass(frozen=True)
class ElasticityRun(Record):
    TYPE: ClassVar[str] = "elasticity-run"
    exp_id: str
    log: str
    program: MotionProgram


@dataclass(frozen=True)
class ElasticityOutcome(Record):
    TYPE: ClassVar[str] = "elasticity-outcome"
    robot: str
    results: tuple[Mapping[str, Any], ...]


@dataclass(frozen=True)
class ElasticityJob(Job):
    """Two-mass fits of each stepped-sine log, from the schedule its program carried."""

    TYPE: ClassVar[str] = "elasticity-job"
    RESULT: ClassVar[type[Record]] = ElasticityOutcome
    robot: str
    lock: tuple[str, ...]
    runs: tuple[ElasticityRun, ...]
    #: the run's report folder: its report.html gains the Bode section (None: no report)
    report_dir: str | None = None
    #: the daemon run and campaign the report names
    run_id: str | None = None
    campaign: str | None = None


@dataclass(frozen=True)
class FeedforwardTable(Record):
    """Model torque (N·m) per setpoint and joint of a parameter set: what a driver that is
    the motion master streams as torque offsets."""

    TYPE: ClassVar[str] = "feedforward-table"
    set_sha256: str
    period_s: float
    tau: tuple[tuple[float, ...], ...]


@dataclass(frozen=True)
class FeedforwardJob(Job):
    """The parameter set's inverse dynamics plus joint friction along setpoints ``q`` (rad,
    one row per ``period_s``; q̇, q̈ by central differences)."""

    TYPE: ClassVar[str] = "feedforward-job"
    RESULT: ClassVar[type[Record]] = FeedforwardTable
    robot: str
    lock: tuple[str, ...]
    parameter_set: ParameterSet
    period_s: float
    q: tuple[tuple[float, ...], ...]


@dataclass(frozen=True)
class DriftFlag(Record):
    TYPE: ClassVar[str] = "drift-flag"
    run_id: str
    parameter: str
    kind: str
    change: float
    sigmas: float
    message: str


@dataclass(frozen=True)
class DriftReport(Record):
    TYPE: ClassVar[str] = "drift-report"
    flags: tuple[DriftFlag, ...]


@dataclass(frozen=True)
class DriftJob(Job):
    """Drift flags of a robot's stored identify records (of one run, or all)."""

    TYPE: ClassVar[str] = "drift-job"
    RESULT: ClassVar[type[Record]] = DriftReport
    robot: str
    results: tuple[Mapping[str, Any], ...]
    run_id: str | None
