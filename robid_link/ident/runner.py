"""One identification job: identify → JSON and report files → history → maybe diagnose (→ its
JSON and figures) → report.html. The CLI, the daemon's worker and the demo all run their
analyses here.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robid_link.ident.data.logs import Log
from robid_link.ident.diagnosis.history import append_record, read_history, result_record
from robid_link.ident.fit.identify import identify
from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.effects import Model
from robid_link.ident.model.robot import Robot
from robid_link.ident.report.figures import residual_figures, write_json, write_report
from robid_link.ident.report.html import write_html_report

if TYPE_CHECKING:  # diagnose (scipy.stats) is imported only when a job diagnoses
    from robid_link.ident.diagnosis.diagnose import Diagnosis
    from robid_link.jobs import ResonanceHint

__all__ = ["ANALYSES", "JobOutcome", "run_job", "release_freed_memory"]

#: the analyses a job can run, in the order they run
ANALYSES = ("identify", "diagnose")


@dataclass
class JobOutcome:
    """What a job produced: the fitted result, the diagnosis, their JSON documents and
    history records (by analysis), the report files written, and report.html."""

    result: IdentResult
    diagnosis: Diagnosis | None = None
    docs: dict[str, dict[str, Any]] = field(default_factory=dict)
    records: dict[str, dict[str, Any]] = field(default_factory=dict)
    report_files: dict[str, list[Path]] = field(default_factory=dict)
    report_html: Path | None = None

    def summaries(self) -> list[str]:
        out = [self.result.summary()] if "identify" in self.docs else []
        return out + ([self.diagnosis.summary()] if self.diagnosis is not None else [])


def release_freed_memory() -> None:
    """Large arrays go back to the system when freed (glibc: a fixed mmap threshold).

    glibc raises its mmap threshold to the size of each large block freed, after which
    blocks of that size come from the heap and stay resident when freed: the process's
    peak then depends on the order of allocations and frees, which numba's threads and the
    scheduler change from run to run. A job allocates its chunk buffers again and again."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt(-3, 1 << 20)  # M_MMAP_THRESHOLD: 1 MiB, fixed
    except (OSError, AttributeError):  # not glibc
        pass


def run_job(robot: Robot, data: Sequence[Log], model: Model, *,
            analyses: Collection[str] = ("identify",),
            validate: Sequence[Log] | None = None, cutoff_hz: float | None = None,
            interval: int = 1, method: str = "ols", weight: str = "bisquare",
            motor_side: bool = False, json_files: Mapping[str, str | Path] | None = None,
            report_dir: str | Path | None = None, history: str | Path | None = None,
            run_id: str | None = None, campaign: str | None = None,
            resonance_hints: Mapping[int, ResonanceHint] | None = None) -> JobOutcome:
    """Run the ``analyses`` (``identify``, ``diagnose``) on one set of inputs.

    The model is fitted once: a diagnosis reuses the identification (see ``diagnose``).
    ``json_files`` maps an analysis to the file its JSON document goes to; ``report_dir``
    gets identify's report files, the diagnosis' residual figures and, last, report.html (with
    the model file's error ladder); ``history`` (a model file) gets one record per analysis,
    after all of them ran (once per ``run_id`` of a daemon run, so a run resumed after a crash
    adds no second record); ``run_id`` and ``campaign`` name a daemon run in the report.
    ``resonance_hints``: per joint, what the diagnosis tells of an
    unexplained resonance (the daemon's campaign language; without, the generic advice).
    """
    release_freed_memory()
    unknown = set(analyses) - set(ANALYSES)
    if unknown or not analyses:
        raise ValueError(f"analyses: {sorted(unknown) or 'none'} (choose from {ANALYSES})")
    json_files = json_files or {}
    res = identify(robot, data, model, validate=validate, cutoff_hz=cutoff_hz,
                   interval=interval, method=method, weight=weight, motor_side=motor_side)
    out = JobOutcome(res)
    if "identify" in analyses:
        out.docs["identify"] = res.to_dict()
        if "identify" in json_files:
            write_json(json_files["identify"], out.docs["identify"])
        if report_dir is not None:
            out.report_files["identify"] = write_report(res, report_dir)
    if "diagnose" in analyses:
        from robid_link.ident.diagnosis.diagnose import diagnose

        dg = diagnose(robot, data, model, validate=validate, cutoff_hz=cutoff_hz,
                      interval=interval, motor_side=motor_side, result=res,
                      resonance_hints=resonance_hints)
        out.diagnosis = dg
        doc = dg.to_dict()
        doc["data_files"] = dg.result.to_dict()["data_files"]
        out.docs["diagnose"] = doc
        if "diagnose" in json_files:
            write_json(json_files["diagnose"], doc)
        if report_dir is not None:
            out.report_files["diagnose"] = residual_figures(dg.residuals, dg.result.joints,
                                                            report_dir)
    out.records = {kind: result_record(kind, doc) for kind, doc in out.docs.items()}
    if run_id is not None:
        for rec in out.records.values():
            rec["run_id"] = run_id
    if history is not None:
        for rec in out.records.values():
            append_record(history, rec)
    if report_dir is not None:
        run = {"run_id": run_id, "campaign": campaign} if run_id else None
        out.report_html = write_html_report(
            report_dir, result=res, diagnosis=out.diagnosis, model_file=history, run=run,
            history=read_history(history) if history else None)
    return out
