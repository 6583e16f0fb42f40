"""``robid demo``: the main job on an embedded default.

Until the daemon exists (issue 5) this runs the worker's loop on a simulated 6-axis robot
whose truth holds an effect the default model does not know: excitation → simulated log →
identify → diagnose → add the suggested effect → identify again → report.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from robid_link.ident.data import write_log_csv
from robid_link.ident.diagnose import diagnose
from robid_link.ident.effects import DEFAULT_MODEL, EffectSpec, save_model
from robid_link.ident.excitation import optimize_fourier
from robid_link.ident.history import append_record, result_record
from robid_link.ident.identify import identify, load_logs
from robid_link.ident.report import history_figure, residual_figures, write_json, write_report
from robid_link.ident.robot import load_robot

__all__ = ["run_demo", "DEMO_ROBOT", "HIDDEN"]

DEMO_ROBOT = Path(__file__).resolve().parent.parent / "examples" / "robots" / "industrial6.yaml"
#: what the default model does not know: cogging on axis 1 (0.6 N·m, every 0.1 rad)
HIDDEN = {"name": "ripple", "joint": 1, "amplitude": 0.6, "period": 0.1}


def run_demo(work: Path, out: Path, json_path: str | None = None) -> int:
    from fakes.plant import Plant, Truth, perturbed_inertials

    robot = load_robot(DEMO_ROBOT)
    print(f"robid demo: {robot.name} ({robot.n} axes), simulated; hidden effect: "
          f"{HIDDEN['name']}@{HIDDEN['joint']}")
    print("  [1/5] designing the excitation (Fourier, condition number of the base regressor)")
    traj, cond = optimize_fourier(robot, harmonics=8, base_hz=0.1, evaluations=600, restarts=1)
    rate = 250.0
    t = np.arange(0.0, 40.0, 1.0 / rate)
    truth = Truth(inertials=perturbed_inertials(robot, seed=11, spread=0.2),
                  effects=({"name": "viscous", "fv": 3.0}, {"name": "coulomb", "fc": 2.0},
                           HIDDEN),
                  noise_tau=0.3, q_resolution=2 * np.pi / 2**20)
    print(f"  [2/5] running it on the simulated robot (condition number {cond:.3g})")
    log = Plant(robot, truth).run(t, *traj.evaluate(t), seed=3)
    path = work / "demo_log.csv"
    write_log_csv(path, log["t"], log["q"], log["tau"])
    data = load_logs(robot, [path])
    model_file = out / "model.yaml"
    out.mkdir(parents=True, exist_ok=True)
    for stale in (model_file, model_file.with_name("model.yaml.history.jsonl")):
        stale.unlink(missing_ok=True)
    save_model(model_file, DEFAULT_MODEL)
    print("  [3/5] identifying the default model")
    first = identify(robot, data, DEFAULT_MODEL)
    append_record(model_file, result_record("identify", first.to_dict()))
    print("  [4/5] diagnosing: where does the model fail, which effect is missing?")
    dg = diagnose(robot, data, DEFAULT_MODEL)
    doc = dg.to_dict()
    append_record(model_file, result_record("diagnose", doc))
    print(dg.summary())
    model = DEFAULT_MODEL
    if dg.suggestions:
        top = dg.suggestions[0]
        model = model.with_added(EffectSpec(top.effect, top.joint,
                                            tuple(sorted(top.hypers.items()))))
        save_model(model_file, model)
    print(f"  [5/5] identifying again with [{', '.join(model.labels())}]")
    final = identify(robot, data, model)
    append_record(model_file, result_record("identify", final.to_dict()))
    print(final.summary())
    files = write_report(final, out)
    files += residual_figures(dg.residuals, dg.result.joints, out)
    records = [json.loads(x) for x in model_file.with_name("model.yaml.history.jsonl")
               .read_text().splitlines()]
    files.append(history_figure(records, out / "error_ladder.png"))
    before, after = first.rmse, final.rmse
    print("\n  error ladder, validation RMSE per joint [N·m]:")
    print("    default model : " + " ".join(f"{x:7.3f}" for x in before))
    print(f"    + {model.labels()[-1]:<12}: " + " ".join(f"{x:7.3f}" for x in after))
    print(f"\nrobid demo: wrote {len(files)} report files to {out}/")
    if json_path:
        write_json(json_path, {"diagnosis": doc, "final": final.to_dict(),
                               "hidden": HIDDEN, "model": model.labels()})
    return 0
