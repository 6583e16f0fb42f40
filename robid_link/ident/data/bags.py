"""ROS recordings as logs: a ROS 2 bag folder (sqlite3 or MCAP storage, with its
``metadata.yaml``), a single ``.mcap`` file or a ROS 1 ``.bag``, read with ``rosbags``.

Joints are matched to the robot by *name* (a joint_state_broadcaster publishes in its own order,
which may change between messages). The measured state comes from ``sensor_msgs/JointState``
(position, velocity, effort) or from a joint trajectory controller's state
(``control_msgs/JointTrajectoryControllerState``: its feedback — ``actual`` before ROS 2 Humble —
and the reference it tracked, kept as the commanded motion). Topics of other types (a
``trajectory_msgs/JointTrajectory`` command, a wrench) are named in a note and not read.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.exceptions import DataError

__all__ = ["is_bag", "read_bag", "BagLog", "JOINT_STATE", "CONTROLLER_STATE"]

JOINT_STATE = "sensor_msgs/msg/JointState"
CONTROLLER_STATE = "control_msgs/msg/JointTrajectoryControllerState"
_COMMAND_TYPES = ("trajectory_msgs/msg/JointTrajectory",)
#: message types whose topics may be read as a log, best first
_STATE_TYPES = (JOINT_STATE, CONTROLLER_STATE)
_WRENCH_TYPES = ("geometry_msgs/msg/WrenchStamped", "geometry_msgs/msg/Wrench")

#: control_msgs' controller state as ROS 2 Humble defines it (a Humble sqlite3 bag carries no
#: message definitions; MCAP files and ROS 1 bags carry their own, which take precedence)
_CONTROLLER_STATE_HUMBLE = "\n".join([
    "std_msgs/Header header", "string[] joint_names",
    *(f"trajectory_msgs/JointTrajectoryPoint {f}"
      for f in ("reference", "feedback", "error", "output", "desired", "actual")),
    "string[] multi_dof_joint_names",
    *(f"trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_{f}"
      for f in ("reference", "feedback", "error", "output", "desired", "actual")),
])

#: most messages read from one topic (an hour at 1 kHz is 3.6 million)
MAX_MESSAGES = 20_000_000


@dataclass
class BagLog:
    """What a bag gave: the arrays in the robot's joint order and where they came from."""

    t: np.ndarray
    q: np.ndarray
    tau: np.ndarray
    qd: np.ndarray | None
    topic: str
    msgtype: str
    #: the commanded positions at the same stamps (a controller state's reference), if any
    q_ref: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    source: dict[str, Any] = field(default_factory=dict)


def is_bag(path: str | Path) -> bool:
    """A ROS recording by its shape: a folder with ``metadata.yaml``, an ``.mcap`` or a
    ``.bag`` file."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix.lower() in (".mcap", ".bag")


def _storage(p: Path) -> str:
    if p.suffix.lower() == ".bag":
        return "ROS 1 bag"
    if p.suffix.lower() == ".mcap":
        return "MCAP file"
    ids = {f.suffix for f in p.iterdir()}
    return "ROS 2 bag (MCAP)" if ".mcap" in ids else "ROS 2 bag (sqlite3)"


def _typestore() -> Any:
    """ROS 2 Humble's message types plus the controller state (bags without definitions)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(_CONTROLLER_STATE_HUMBLE, CONTROLLER_STATE))
    return store


def _open(p: Path) -> Any:
    from rosbags.highlevel import AnyReader

    if p.is_dir() and not (p / "metadata.yaml").is_file():
        raise DataError(f"{p}: a folder, but not a ROS 2 bag (no metadata.yaml)")
    try:
        reader = AnyReader([p], default_typestore=_typestore())
        reader.open()
    except FileNotFoundError as err:
        raise DataError(f"{p}: log file not found") from err
    except Exception as err:  # rosbags raises its own and sqlite3/struct errors on damage
        raise DataError(f"{p}: not a readable {_storage(p)} ({_reason(err)})") from err
    return reader


def _reason(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text[:120]}" if text else type(err).__name__


def _choose_topic(p: Path, reader: Any, topic: str | None) -> tuple[str, str, list[str]]:
    """(topic, msgtype, notes): the asked topic, else the one joint-state topic
    (``/joint_states`` among several), else a controller state topic."""
    types = {c.topic: c.msgtype for c in reader.connections}
    notes = [f"{p.name}: {'wrench' if m in _WRENCH_TYPES else 'commanded trajectory'} topic "
             f"{t} not read (the log is the measured joint state)"
             for t, m in sorted(types.items()) if m in (*_WRENCH_TYPES, *_COMMAND_TYPES)]
    if topic is not None:
        if topic not in types:
            raise DataError(f"{p}: no topic {topic} (topics: {', '.join(sorted(types)) or 'none'})")
        if types[topic] not in _STATE_TYPES:
            raise DataError(f"{p}: topic {topic} holds {types[topic]}, expected "
                            f"{' or '.join(_STATE_TYPES)} (positions and efforts of joints)")
        return topic, types[topic], notes
    for msgtype in _STATE_TYPES:
        found = sorted(t for t, m in types.items() if m == msgtype)
        if len(found) == 1:
            return found[0], msgtype, notes
        if "/joint_states" in found:
            others = ", ".join(t for t in found if t != "/joint_states")
            return "/joint_states", msgtype, [*notes, f"{p.name}: read /joint_states; also "
                                              f"{others} (pick one with --topic)"]
        if found:
            raise DataError(f"{p}: {len(found)} {msgtype} topics ({', '.join(found)}): "
                            "pick one with --topic")
    shown = ", ".join(f"{t} ({m})" for t, m in sorted(types.items())) or "none"
    raise DataError(f"{p}: no {JOINT_STATE} or {CONTROLLER_STATE} topic (topics: {shown})")


@dataclass
class _Rows:
    stamp: list[float] = field(default_factory=list)
    received: list[float] = field(default_factory=list)
    q: list[np.ndarray] = field(default_factory=list)
    qd: list[np.ndarray | None] = field(default_factory=list)
    tau: list[np.ndarray | None] = field(default_factory=list)
    ref: list[np.ndarray | None] = field(default_factory=list)
    foreign: int = 0  # messages that hold none of the robot's joints (a gripper's)
    extra: set[str] = field(default_factory=set)


def _point(msg: Any, msgtype: str) -> tuple[Any, Any, Sequence[str]]:
    """(measured point, reference point or None, joint names) of one message."""
    if msgtype == JOINT_STATE:
        return msg, None, msg.name
    feedback = getattr(msg, "feedback", None)
    if feedback is None or not len(feedback.positions):  # ROS 1 / before Humble: actual
        feedback = getattr(msg, "actual", feedback)
    ref = getattr(msg, "reference", None)
    if ref is None or not len(ref.positions):
        ref = getattr(msg, "desired", ref)
    return feedback, ref, msg.joint_names


def _take(rows: _Rows, p: Path, k: int, names: Sequence[str], order: Sequence[str],
          point: Any, ref: Any, msgtype: str) -> None:
    index = {nm: i for i, nm in enumerate(names)}
    if len(index) != len(names):
        raise DataError(f"{p}: message {k + 1} names a joint twice ({', '.join(names)})")
    have = [nm for nm in order if nm in index]
    if not have:
        rows.foreign += 1
        return
    if len(have) != len(order):
        missing = [nm for nm in order if nm not in index]
        raise DataError(f"{p}: message {k + 1} lacks joint(s) {', '.join(missing)} of the "
                        f"robot (it names {', '.join(names)})")
    rows.extra.update(nm for nm in names if nm not in set(order))
    cols = [index[nm] for nm in order]
    pos = np.asarray(point.position if msgtype == JOINT_STATE else point.positions, float)
    vel = np.asarray(point.velocity if msgtype == JOINT_STATE else point.velocities, float)
    eff = np.asarray(point.effort, float)
    if pos.size != len(names):
        raise DataError(f"{p}: message {k + 1} has {pos.size} positions for {len(names)} "
                        "joint names")
    rows.q.append(pos[cols])
    rows.qd.append(vel[cols] if vel.size == len(names) else None)
    rows.tau.append(eff[cols] if eff.size == len(names) else None)
    refpos = np.asarray(ref.positions, float) if ref is not None else np.empty(0)
    rows.ref.append(refpos[cols] if refpos.size == len(names) else None)


def _messages(reader: Any, topic: str, p: Path) -> Iterator[tuple[int, Any]]:
    conns = [c for c in reader.connections if c.topic == topic]
    try:
        for k, (conn, stamp, raw) in enumerate(reader.messages(connections=conns)):
            if k >= MAX_MESSAGES:
                raise DataError(f"{p}: topic {topic} has more than {MAX_MESSAGES} messages")
            yield stamp, reader.deserialize(raw, conn.msgtype)
    except DataError:
        raise
    except Exception as err:  # a truncated or damaged file fails inside rosbags
        raise DataError(f"{p}: topic {topic} unreadable, the recording may be truncated "
                        f"({_reason(err)})") from err


def read_bag(path: str | Path, joint_names: Sequence[str], topic: str | None = None) -> BagLog:
    """Read one topic of a recording into arrays in ``joint_names``' order; a DataError
    names the file and what is wrong (missing joints, no effort, an unreadable bag)."""
    p = Path(path)
    reader = _open(p)
    try:
        chosen, msgtype, notes = _choose_topic(p, reader, topic)
        rows = _Rows()
        for k, (received, msg) in enumerate(_messages(reader, chosen, p)):
            point, ref, names = _point(msg, msgtype)
            before = len(rows.q)
            _take(rows, p, k, names, joint_names, point, ref, msgtype)
            if len(rows.q) > before:
                stamp = msg.header.stamp
                rows.stamp.append(stamp.sec + 1e-9 * stamp.nanosec)
                rows.received.append(1e-9 * received)
    finally:
        reader.close()
    return _arrays(p, rows, chosen, msgtype, notes, joint_names)


def _arrays(p: Path, rows: _Rows, topic: str, msgtype: str, notes: list[str],
            order: Sequence[str]) -> BagLog:
    where = f"{p}: topic {topic}"
    if not rows.q:
        extra = f" ({rows.foreign} messages name none of them)" if rows.foreign else ""
        raise DataError(f"{where}: no message holds the robot's joints {', '.join(order)}{extra}")
    if rows.extra:
        notes.append(f"{p.name}: joints {', '.join(sorted(rows.extra))} of {topic} are not the "
                     "robot's; ignored")
    if rows.foreign:
        notes.append(f"{p.name}: {rows.foreign} messages of {topic} hold none of the robot's "
                     "joints (another publisher); ignored")
    no_effort = sum(e is None for e in rows.tau)
    if no_effort == len(rows.tau):
        raise DataError(f"{where}: effort is empty in every message (the recording holds no "
                        "torques; record the drives' effort)")
    if no_effort:
        raise DataError(f"{where}: effort is empty in {no_effort} of {len(rows.tau)} messages")
    stamp = np.asarray(rows.stamp)
    if np.all(stamp == 0) or np.any(np.diff(stamp) <= 0):
        notes.append(f"{p.name}: header stamps of {topic} are "
                     f"{'zero' if np.all(stamp == 0) else 'not increasing'}; the bag's receive "
                     "times are used (they carry the transport's delay and jitter)")
        stamp = np.asarray(rows.received)
    tau = np.vstack([e for e in rows.tau if e is not None])  # none is None (refused above)
    t0 = float(stamp[0])
    source = {"format": _storage(p), "topic": topic, "msgtype": msgtype,
              "t0_unix_s": t0, "duration_s": float(stamp[-1] - t0), "messages": len(rows.q)}
    return BagLog(stamp - t0, np.vstack(rows.q), tau, _stacked(rows.qd), topic, msgtype,
                  _stacked(rows.ref), notes, source)


def _stacked(rows: list[np.ndarray | None]) -> np.ndarray | None:
    """The rows as one array when every message had them, else None."""
    given = [v for v in rows if v is not None]
    return np.vstack(given) if len(given) == len(rows) else None
