"""Operator output: results compared across runs and robots, progress lines."""

from __future__ import annotations

import io

from robid_link.cli.runs import format_results, format_runs, wait_for_run


def _result(run: str, robot: str, rmse: list[float], kind: str = "identify") -> dict:
    return {"run_id": run, "robot": robot, "kind": kind,
            "record": {"rmse": rmse, "relative_error": 0.05}}


def test_results_compare_each_robot_with_its_previous_run() -> None:
    text = format_results([_result("r1", "arm3", [1.0, 2.0, 3.0]),
                           _result("r2", "industrial6", [1.0] * 6),
                           _result("r3", "arm3", [1.0, 1.0, 3.0])])
    lines = text.splitlines()
    assert "vs previous" not in lines[0] and "vs previous" not in lines[1]
    assert lines[2].endswith("vs previous: joint 2 -50.0 %")
    assert "rel 5.00 %" in lines[0]
    assert format_results([]) == "no results yet"


def test_runs_table_and_progress(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    runs = [{"run_id": "r1", "campaign": "nightly", "trigger": "timer", "state": "failed",
             "progress": {"stored": 1, "total": 2}, "error": "unsafe program refused: x",
             "step": None}]
    assert "unsafe program refused" in format_runs(runs)
    states = iter([{**runs[0], "state": "running", "step": "experiment 2/2 friction",
                    "error": None}, runs[0]])
    import robid_link.cli.runs as cmd

    monkeypatch.setattr(cmd, "request", lambda path, req: {"runs": [next(states)]})
    out = io.StringIO()
    final = wait_for_run("sock", "r1", poll_s=0.0, stream=out)
    assert final["state"] == "failed"
    text = out.getvalue()
    assert "[##########..........] 1/2 logs  running: experiment 2/2 friction" in text
    assert "run r1 failed: unsafe program refused: x" in text


def test_results_compare_stiffness_with_the_previous_run() -> None:
    from robid_link.cli.runs import format_results

    def rec(k: float) -> dict:
        return {"experiments": [{"experiment": "stiff", "result": {"joints": [
            {"joint": 1, "k": k, "d": 30.0, "f_res_hz": 14.0}]}}]}

    text = format_results([
        {"run_id": "r1", "robot": "arm", "kind": "elasticity", "record": rec(3.0e4)},
        {"run_id": "r2", "robot": "arm", "kind": "elasticity", "record": rec(2.7e4)}])
    lines = text.splitlines()
    assert "joint 1: K 3e+04, D 30, f_res 14 Hz" in lines[0]
    assert lines[1].endswith("K vs previous -10.0 %")
