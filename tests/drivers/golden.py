"""Helpers of the golden-transcript tests (``tests/golden/<protocol>/``): the transcripts,
hand-written from each protocol's description, the program and log they carry, and a
controller core that answers with that log (so every answer of a peer is known in advance)."""

from __future__ import annotations

import hashlib
import re
import threading
from pathlib import Path
from typing import Any

import yaml

from robid_link.fakes.controller import ControllerCore, RunResult, default_truth
from robid_link.ident.model.robot import Robot
from robid_link.jobs import MotionProgram

GOLDEN = Path(__file__).resolve().parents[1] / "golden"
_MARK = re.compile(r"<<(\w+)>>")


def load(protocol: str, name: str) -> Any:
    """A transcript (YAML) of ``tests/golden/<protocol>/``."""
    return yaml.safe_load((GOLDEN / protocol / name).read_text())


def text(protocol: str, name: str) -> str:
    return (GOLDEN / protocol / name).read_text()


def fill(value: Any, names: dict[str, Any]) -> Any:
    """``value`` with every ``<<name>>`` replaced (a whole-string mark keeps the value's type)."""
    if isinstance(value, str):
        whole = _MARK.fullmatch(value)
        if whole:
            return names[whole.group(1)]
        return _MARK.sub(lambda m: str(names[m.group(1)]), value)
    if isinstance(value, list):
        return [fill(v, names) for v in value]
    if isinstance(value, dict):
        return {fill(k, names): fill(v, names) for k, v in value.items()}
    return value


def common() -> dict[str, Any]:
    """The program, log and parameter set every transcript uses (``common.yaml``), checked
    against their stated SHA-256 and sizes (the hand-written numbers must be right)."""
    doc = load(".", "common.yaml")
    names: dict[str, Any] = {}
    for key, entry in doc.items():
        data = entry["text"].encode()
        assert hashlib.sha256(data).hexdigest() == entry["sha256"], f"{key}: sha256"
        assert len(data) == entry["size"], f"{key}: size"
        names[key] = data
        names[f"{key}_sha256"] = entry["sha256"]
        names[f"{key}_size"] = entry["size"]
    return names


def program(names: dict[str, Any], exp_id: str = "exp1") -> MotionProgram:
    return MotionProgram(exp_id, {"traj.csv": names["traj_csv"],
                                  "traj.yaml": names["traj_yaml"]}, 0.02)


class ScriptedCore(ControllerCore):
    """A controller core whose every run answers the transcript's log. ``gate`` (when given)
    holds each run until the test opens it, so the moment an answer comes is the test's."""

    def __init__(self, robot: Robot, log: bytes, gate: threading.Event | None = None) -> None:
        super().__init__(robot, default_truth(robot, rate_hz=100.0))
        self.log, self.gate = log, gate
        self.runs: list[tuple[str, str, bytes, bytes | None]] = []
        self.loaded: list[bytes] = []

    def run(self, exp_id: str, nonce: str, csv: bytes, header: bytes | None = None
            ) -> RunResult:
        self.runs.append((exp_id, nonce, csv, header))
        self.handled.append((exp_id, nonce))
        if self.gate is not None:
            assert self.gate.wait(30), "the test never opened the gate"
        return RunResult(exp_id, nonce, None, self.log, self.log)

    def receive_parameters(self, body: bytes) -> None:
        self.loaded.append(body)
