"""``robid demo``: the main job on an embedded default, through the real link.

A temporary share and state dir; the fake controller (a thread) over a simulated 6-axis robot
whose truth holds an effect the default model does not know; the daemon; one campaign
(excitation → generate/give/take/load → identification → diagnosis) started over the control
socket with a progress display; then the suggested effect is added to the model file and the
stored logs are identified again: the error ladder. Report files go to ``--out``; its
report.html is the first run's, with the error ladder and the verification's tracking added.
"""

from __future__ import annotations

import asyncio
import shutil
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from robid_link.config import load_daemon_config
from robid_link.exceptions import RobidError

__all__ = ["run_demo", "demo_truth", "DEMO_ROBOT", "HIDDEN", "RIGID", "QUICK_RIGID"]

DEMO_ROBOT = Path(str(resources.files("robid_link.examples.robots") / "industrial6.yaml"))
#: what the default model does not know: cogging on axis 1 (0.6 N·m, every 0.1 rad)
HIDDEN = {"name": "ripple", "joint": 1, "amplitude": 0.6, "period": 0.1}
RIGID = {"kind": "rigid_body", "duration_s": 40, "harmonics": 8, "base_hz": 0.1,
         "evaluations": 600, "restarts": 1, "rate_hz": 250}
#: ``--quick`` (the tests of every link): half the excitation, a tenth of the optimiser's work;
#: the same story (the hidden effect found, the error falls once it is added), a third of the
#: time
QUICK_RIGID = {**RIGID, "duration_s": 20, "base_hz": 0.2, "evaluations": 60}
#: first: excite, identify, diagnose (what is the model missing?)
CAMPAIGN = {"experiments": [RIGID], "diagnose": True, "timeout_s": 180, "retries": 1,
            "backoff_s": 1.0}
#: then, with the effect added: the verification path on the controller's CAD model (20 %
#: off, no friction), identify, hand the parameter set over, the verification path again
CALIBRATE = {**CAMPAIGN, "experiments": [RIGID, "upload", {"kind": "verify"}],
             "diagnose": False}


def _setup(work: Path, out: Path, driver: dict[str, Any], calibrate: bool = True,
           quick: bool = False) -> tuple[Path, Path]:
    model = out / "model.yaml"
    out.mkdir(parents=True, exist_ok=True)
    for stale in (model, model.with_name("model.yaml.history.jsonl")):
        stale.unlink(missing_ok=True)
    from robid_link.ident.model.effects import DEFAULT_MODEL, save_model

    save_model(model, DEFAULT_MODEL)
    cfg: dict[str, Any] = {"robot": str(DEMO_ROBOT), "state_dir": str(work / "state"),
                           "control_socket": str(work / "control.sock"),
                           "driver": driver,
                           "campaigns": {"demo": {**CAMPAIGN, "model": str(model)}}}
    if calibrate:  # only over a link that can upload a parameter set
        cfg["campaigns"]["calibrate"] = {**CALIBRATE, "model": str(model)}
    if quick:
        for camp in cfg["campaigns"].values():
            camp["experiments"] = [QUICK_RIGID if e is RIGID else e for e in camp["experiments"]]
    path = work / "daemon.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path, model


def demo_truth(robot: Any) -> Any:
    """The demo cell's plant (``fakes.plant.Truth``): the robot 20 % off its CAD inertials,
    viscous and Coulomb friction, the hidden effect, torque noise, a 20-bit encoder, a closed
    loop at 1 kHz."""
    from robid_link.link.registry import fake_module

    plant = fake_module("plant")
    return plant.Truth(inertials=plant.perturbed_inertials(robot, seed=11, spread=0.2),
                       effects=({"name": "viscous", "fv": 3.0},
                                {"name": "coulomb", "fc": 2.0}, HIDDEN),
                       noise_tau=0.3, q_resolution=2 * 3.141592653589793 / 2**20,
                       rate_hz=1000.0, mode="closed_loop",
                       controller={"rate_hz": 1000.0, "bandwidth_hz": 8.0})


def _controller(driver: str, workdir: Path) -> Any:
    """The fake controller of ``driver``'s protocol over the demo robot (not started)."""
    from robid_link.ident.model.robot import load_robot
    from robid_link.link.registry import fake_module

    robot = load_robot(DEMO_ROBOT)
    workdir.mkdir(parents=True)
    return fake_module("controller").make_peer(driver, robot, demo_truth(robot), workdir,
                                               seed=3)


async def _campaign(cfg_path: Path, log_file: Path, name: str = "demo") -> dict[str, Any]:
    from robid_link.cli.runs import wait_for_run
    from robid_link.link.control import PREFLIGHT_TIMEOUT_S, request
    from robid_link.link.daemon import Daemon
    from robid_link.link.notify import setup_logging

    cfg = load_daemon_config(cfg_path)
    with open(log_file, "a") as log:
        setup_logging("info", log)
        try:
            async with Daemon(cfg, env={}):
                sock = cfg.control_socket
                ans = await asyncio.to_thread(request, sock, {"cmd": "start",
                                                              "campaign": name},
                                              PREFLIGHT_TIMEOUT_S)
                print(f"  campaign '{name}' started: run {ans['run_id']}")
                run = await asyncio.to_thread(wait_for_run, sock, ans["run_id"])
                res = await asyncio.to_thread(request, sock, {"cmd": "results",
                                                              "run_id": run["run_id"]})
                return {"run": run, "results": res["results"]}
        finally:
            setup_logging("info")  # the log file closes with this block


def _add_suggestion(doc: dict[str, Any], model_file: Path) -> Any:
    """The diagnosis's top suggestion added to the model file (with its hyper-parameters)."""
    from robid_link.ident.model.effects import EffectSpec, load_model, save_model

    diag = next(r["record"] for r in doc["results"] if r["kind"] == "diagnose")
    if not diag["suggestions"]:
        return None
    top = diag["suggestions"][0]
    spec = EffectSpec(top["effect"], top["joint"],
                      tuple(sorted((top.get("hyper_parameters") or {}).items())), top.get("side"))
    save_model(model_file, load_model(model_file).with_added(spec))
    print(f"  the diagnosis suggests {spec.label()}: added to {model_file}")
    return spec


def _tracking(results: list[dict[str, Any]]) -> dict[str, Any] | None:
    """``{before: {tool_rms_mm, tool_max_mm, joint_rms, …}, after: {…}}`` of the run."""
    by = {r["kind"]: r["record"]["tracking"] for r in results
          if r["kind"] in ("verify_before", "verify_after")}
    if len(by) != 2:
        return None
    return {"before": by["verify_before"], "after": by["verify_after"]}


def run_demo(work: Path, out: Path, json_path: str | None = None,
             driver: str = "file_share", quick: bool = False) -> int:
    from robid_link.ident.diagnosis.history import read_history
    from robid_link.ident.fit.identify import load_logs
    from robid_link.ident.model.effects import load_model
    from robid_link.ident.model.robot import load_robot
    from robid_link.ident.report.figures import history_figure, write_json
    from robid_link.ident.runner import run_job

    out = out.resolve()  # the daemon's config lives elsewhere: paths in it are absolute
    print(f"robid demo: industrial6 (6 axes), simulated cell; hidden effect: "
          f"{HIDDEN['name']}@{HIDDEN['joint']} (the default model does not know it)")
    print(f"  fake controller ({driver}) and daemon with a temporary state dir; "
          f"daemon log: {out / 'daemon.log'}")
    from robid_link.link.driver import CAP_UPLOAD
    from robid_link.link.registry import driver_class

    can_upload = CAP_UPLOAD in driver_class(driver).capabilities
    with _controller(driver, work / "cell") as peer:
        cfg_path, model_file = _setup(work, out, peer.driver_options(), can_upload, quick)
        doc = asyncio.run(_campaign(cfg_path, out / "daemon.log"))
        run = doc["run"]
        if run["state"] != "completed":
            raise RobidError(f"demo campaign failed: {run['error']}")
        report = work / "state" / "reports" / run["run_id"]
        print((report / "summary.txt").read_text())
        spec = _add_suggestion(doc, model_file)
        cal = None
        if can_upload:
            print("  calibrate and verify: the verification path on the controller's CAD "
                  "model, identification" + (f" with {spec.label()}" if spec else "")
                  + ", upload, the path again")
            cal = asyncio.run(_campaign(cfg_path, out / "daemon.log", "calibrate"))
        else:
            print(f"  calibrate and verify: skipped, the {driver} link cannot upload a "
                  "parameter set")
    files = []
    for f in sorted(report.iterdir()):
        shutil.copy2(f, out / f.name)
        files.append(out / f.name)
    first = next(r["record"] for r in doc["results"] if r["kind"] == "identify")
    robot = load_robot(DEMO_ROBOT)
    model = load_model(model_file)
    final_rmse = first["rmse"]
    if spec is not None:
        print(f"  identifying the first run's logs again with {spec.label()}")
        logs = [str(work / "state" / "logs" / e["log_sha"][:2] / f"{e['log_sha']}.csv")
                for e in run["experiments"] if e["kind"] != "verify"]
        final = run_job(robot, load_logs(robot, logs), model, report_dir=out / "final",
                        history=model_file)
        files += final.report_files["identify"]
        final_rmse = final.result.rmse.tolist()
    ladder = read_history(model_file)
    files.append(history_figure(ladder, out / "error_ladder.png"))
    print("\n  error ladder, validation RMSE per joint [N·m]:")
    print("    default model : " + " ".join(f"{x:7.3f}" for x in first["rmse"]))
    if spec is not None:
        print(f"    + {model.labels()[-1]:<12}: " + " ".join(f"{x:7.3f}" for x in final_rmse))
    if cal is not None and cal["run"]["state"] != "completed":
        raise RobidError(f"demo calibration failed: {cal['run']['error']}")
    tracking = _tracking(cal["results"]) if cal is not None else None
    from robid_link.ident.report.html import add_to_report

    page = add_to_report(out / "report.html", history=ladder, tracking=tracking)
    if tracking:
        from robid_link.ident.report.figures import tracking_figure

        files.append(tracking_figure(tracking, out / "tracking.png"))
        b, a = tracking["before"], tracking["after"]
        print("\n  verification path, tool position error (controller on CAD → on the "
              "identified parameter set):")
        print(f"    RMS {b['tool_rms_mm']:.3f} → {a['tool_rms_mm']:.3f} mm "
              f"({b['tool_rms_mm'] / max(a['tool_rms_mm'], 1e-12):.1f}× lower), max "
              f"{b['tool_max_mm']:.3f} → {a['tool_max_mm']:.3f} mm, after the stop "
              f"{b['residual_mm']:.3f} → {a['residual_mm']:.3f} mm")
    print(f"\nrobid demo: run {run['run_id']} completed; {len(files)} report files in {out}/")
    print(f"  open the report: {page}")
    if json_path:
        write_json(json_path, {"run": run, "results": doc["results"], "hidden": HIDDEN,
                               "model": model.labels(), "final_rmse": final_rmse,
                               "tracking": tracking})
    return 0
