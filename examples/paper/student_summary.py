"""The distilled student over every run: its honest ceiling, its offline gain, its screen and its test, in one table.

    python examples/paper/student_summary.py          # docs/results/student_summary.{json,md,png}

Reads each run's committed results in ``results`` (a run is ``<backbone>_<task>_s<seed>``, named by its screen,
``student_screen_<run>.json``): the scorer ladder (the ``benchmarks`` of every ``scorer_benchmark*.json``: the
honest ceiling, the student's out-of-fold AUC and offline gain), the validation screen and, for a run whose screen
passed, the test (``student_test_<run>.json``). Pools the test episodes per backbone: the mean gain over the tested
runs, the paired sign test over all their episodes, and Table 1's mean: per task, the mean gain over its seeds,
where a run whose screen failed counts as gain 0 (the preregistered rule), then the mean over tasks. A run that
passed and has no test yet is left out of both means. Every number comes from those files; nothing is run.

The gate (``docs/results/student_gate_prereg.json``): a run deploys the student only where its offline gain is at
least ``gate``; elsewhere the base policy runs and its Table 1 gain is 0. Table 1's mean is reported ungated and
gated, over every run and over the runs the gate is judged on: those it was not chosen on (not in ``GATE_SEEN``).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.branching.outcome_noise import honest_ceiling
from torchrl_dalir.branching.scorer_benchmark import all_draws, load_benchmark
from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.compare import BASE, screen_passed, sign_test
from torchrl_dalir.evaluation.plots import plot_metric_by_task
from torchrl_dalir.utils import atomic_write, provenance

ROOT = Path(__file__).resolve().parents[2]
STUDENT = "critic"  # critic_screen.py's name of the reranked method
# the runs the gate's threshold was chosen on (student_gate_prereg.json): exploratory for the gate, never its evidence
GATE_SEEN = (
    "dp_door_s0", "dp_pen_s0", "dp_pick_place_wall_s0", "fm_disassemble_s0", "fm_door_s0", "fm_door_s1",
    "fm_door_s2", "fm_pen_s0", "fm_pen_s1", "fm_pen_s2", "fm_pick_place_wall_s0", "fm_shelf_place_s0",
    "fm_stick_pull_s0",
)  # fmt: skip


@dataclass
class Config:
    results: str = str(ROOT / "docs" / "results")  # the committed result files
    benchmarks: str = str(ROOT / "benchmarks" / "scorer")  # the runs' benchmark files (the ceiling's standard error)
    out: str = str(ROOT / "docs" / "results" / "student_summary")  # <out>.json, <out>.md and <out>.png
    gate: float = 0.02  # deploy the student only where its offline gain is at least this (student_gate_prereg.json)
    gate_seen: list[str] = field(default_factory=lambda: list(GATE_SEEN))  # runs the gate was chosen on


def episodes(result: dict) -> dict:
    """A screen's or test's base and student success rates, paired counts and episodes."""
    methods, paired = result["methods"], result["paired"]
    return {
        "episodes": methods[BASE]["episodes"],
        "base": methods[BASE]["success_rate"],
        "student": methods[STUDENT]["success_rate"],
        "won": paired["dalir_only"],
        "lost": paired["base_only"],
        "p_value": paired["p_value"],
    }


def run_rows(results: Path, benchmarks: Path, gate: float, gate_seen: list[str]) -> list[dict]:
    """One row per screened run: the ladder's rungs (the honest ceiling's standard error over decisions from the
    run's benchmark file), the screen, where it exists the test, and the gate: ``deployed`` where the student's
    offline gain is at least ``gate``, ``gate_judged`` where the run is not in ``gate_seen``."""
    ladders = {}
    for path in sorted(results.glob("scorer_benchmark*.json")):
        ladders.update(json.loads(path.read_text())["benchmarks"])
    rows = []
    for screen in sorted(results.glob("student_screen_*_s[0-9]*.json")):
        run = screen.stem.removeprefix("student_screen_")
        if run not in ladders:
            raise FileNotFoundError(f"{screen.name} has no ladder: no scorer_benchmark*.json in {results} holds {run}")
        ladder, test = ladders[run], results / f"student_test_{run}.json"
        ceiling = honest_ceiling(all_draws(load_benchmark(benchmarks / f"{run}.pt")[0]))
        if abs(ceiling["honest_gain"] - ladder["honest_ceiling"]["honest_gain"]) > 1e-6:
            raise ValueError(f"{benchmarks / run}.pt is not the benchmark its ladder measured: another honest ceiling")
        backbone, rest = run.split("_", 1)
        task, seed = rest.rsplit("_s", 1)
        screen_result = json.loads(screen.read_text())
        screened = episodes(screen_result)
        rows.append(
            {
                "run": run,
                "backbone": backbone,
                "task": task.replace("_", "-"),
                "seed": int(seed),
                "split_decisions": ladder["split_decisions"],
                "honest_gain": ceiling["honest_gain"],
                "honest_gain_se": ceiling["honest_gain_se"],
                "student_auc": ladder["student"]["auc"],
                "student_gain": ladder["student"]["gain"],
                "screen": screened,
                "passed": screen_passed(screen_result["paired"]),
                "test": episodes(json.loads(test.read_text())) if test.exists() else None,
                "deployed": ladder["student"]["gain"] >= gate,
                "gate_judged": run not in gate_seen,
            }
        )
    return rows


def test_gain(row: dict, gated: bool = False) -> float | None:
    """A run's test gain for Table 1: the student's minus the base policy's success rate; 0 where the screen
    failed (no test episode is run) or, ``gated``, where the gate keeps the base policy; None where the screen
    passed and the test has not run yet (gated or not, so both means hold the same runs)."""
    gain = row["test"]["student"] - row["test"]["base"] if row["test"] else (None if row["passed"] else 0.0)
    return 0.0 if gated and gain is not None and not row["deployed"] else gain


def per_task(rows: list[dict]) -> list[dict]:
    """Table 1's cells: per backbone and task, the seeds with a Table 1 gain and its mean over them, ungated and
    gated, beside the mean over the same seeds of the honest ceiling and of the student's offline gain (what the
    first decision's candidates allow, and what the student takes of it)."""
    cells = {}
    for row in rows:
        if test_gain(row) is not None:
            cells.setdefault((row["backbone"], row["task"]), []).append(row)
    return [
        {
            "backbone": backbone,
            "task": task,
            "seeds": sorted(row["seed"] for row in runs),
            "mean_gain": sum(test_gain(row) for row in runs) / len(runs),
            "mean_gain_gated": sum(test_gain(row, gated=True) for row in runs) / len(runs),
            "mean_ceiling": sum(row["honest_gain"] for row in runs) / len(runs),
            "mean_offline": sum(row["student_gain"] for row in runs) / len(runs),
        }
        for (backbone, task), runs in sorted(cells.items())
    ]


def pooled(rows: list[dict]) -> dict:
    """Per backbone with a Table 1 cell: over the runs with a test, the mean gain (points), wins, losses and the
    sign test; Table 1's mean over the backbone's tasks of each task's mean over its seeds (:func:`per_task`, a
    failed screen counts 0), ungated as ``table1_gain`` and gated as ``table1_gain_gated``, over ``table1_tasks``
    tasks of ``table1_runs`` runs, and the same mean of the honest ceiling (``table1_ceiling``) and of the
    student's offline gain (``table1_offline``); ``deployed``: the sign test over the tested runs the gate deploys."""
    table = {}
    for backbone in sorted({row["backbone"] for row in rows}):
        runs = [row for row in rows if row["backbone"] == backbone]
        tests = [row["test"] for row in runs if row["test"]]
        deployed = [row["test"] for row in runs if row["test"] and row["deployed"]]
        if cells := per_task(runs):
            gain = sum(t["student"] - t["base"] for t in tests) / len(tests) if tests else float("nan")
            table[backbone] = {
                "runs": len(tests),
                "mean_gain": gain,
                **sign_test(sum(t["lost"] for t in tests), sum(t["won"] for t in tests)),
                "table1_tasks": len(cells),
                "table1_runs": sum(len(cell["seeds"]) for cell in cells),
                "table1_gain": sum(cell["mean_gain"] for cell in cells) / len(cells),
                "table1_gain_gated": sum(cell["mean_gain_gated"] for cell in cells) / len(cells),
                "table1_ceiling": sum(cell["mean_ceiling"] for cell in cells) / len(cells),
                "table1_offline": sum(cell["mean_offline"] for cell in cells) / len(cells),
                "deployed": {
                    "runs": len(deployed),
                    **sign_test(sum(t["lost"] for t in deployed), sum(t["won"] for t in deployed)),
                },
            }
    return table


def pool_lines(pools: dict, scope: str) -> list[str]:
    """One line per backbone: the tested runs' pooled test, Table 1's mean ungated and gated, the deployed runs."""
    lines = []
    for backbone, pool in pools.items():
        deployed = pool["deployed"]
        tested = (
            f"{pool['runs']} tested runs, mean test gain {100 * pool['mean_gain']:+.1f} points, {pool['dalir_only']} "
            f"won / {pool['base_only']} lost (sign test p = {pool['p_value']:.2g})"
            if pool["runs"]
            else "no tested run"
        )
        lines.append(
            f"\n{backbone.upper()}, {scope}: {tested}; "
            f"Table 1's mean over {pool['table1_tasks']} tasks ({pool['table1_runs']} screened runs; a failed screen "
            f"counts 0): {100 * pool['table1_gain']:+.1f} points, gated {100 * pool['table1_gain_gated']:+.1f} "
            f"(tested runs the gate deploys: {deployed['runs']}, {deployed['dalir_only']} won / "
            f"{deployed['base_only']} lost, p = {deployed['p_value']:.2g}); the same mean of the honest ceiling: "
            f"{100 * pool['table1_ceiling']:+.1f} points, of the student's offline gain: "
            f"{100 * pool['table1_offline']:+.1f}."
        )
    return lines


def markdown(rows: list[dict], pools: dict, judged: dict, cells: list[dict], gate: float) -> str:
    lines = [
        "| run | split decisions | honest ceiling (± SE) | student offline: AUC / gain "
        f"| validation: base -> student (won / lost) | test: base -> student (won / lost, p) "
        f"| gate (offline gain >= {100 * gate:+.0f}) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        screen, test = row["screen"], row["test"]
        tested = (
            f"{100 * test['base']:.0f} -> {100 * test['student']:.0f} % ({test['won']} / {test['lost']}, "
            f"p = {test['p_value']:.2g})"
            if test
            else ("not run yet" if row["passed"] else "not run (screen failed)")
        )
        gated = ("student" if row["deployed"] else "base") + ("" if row["gate_judged"] else " (seen)")
        lines.append(
            f"| {row['run']} | {row['split_decisions']} | "
            f"{100 * row['honest_gain']:+.1f} ± {100 * row['honest_gain_se']:.1f} | "
            f"{row['student_auc']:.2f} / {100 * row['student_gain']:+.1f} | {100 * screen['base']:.0f} -> "
            f"{100 * screen['student']:.0f} % ({screen['won']} / {screen['lost']}) | {tested} | {gated} |"
        )
    lines += pool_lines(pools, "every run (for the gate, the seen runs are exploratory)")
    lines += pool_lines(judged, "only the runs the gate is judged on (not seen when it was chosen)")
    if not judged:
        lines.append("\nThe gate is judged on no run yet: every run so far is one it was chosen on (seen).")
    lines += [
        "",
        "| backbone | task | seeds | mean test gain (failed screen = 0) | gated | honest ceiling | student offline |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for cell in cells:
        seeds = ", ".join(str(seed) for seed in cell["seeds"])
        lines.append(
            f"| {cell['backbone'].upper()} | {cell['task']} | {seeds} | {100 * cell['mean_gain']:+.1f} "
            f"| {100 * cell['mean_gain_gated']:+.1f} | {100 * cell['mean_ceiling']:+.1f} "
            f"| {100 * cell['mean_offline']:+.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    rows = run_rows(Path(cfg.results), Path(cfg.benchmarks), cfg.gate, cfg.gate_seen)
    if not rows:
        raise FileNotFoundError(f"no student_screen_<run>.json in {cfg.results}: screen a student first")
    cells, pools = per_task(rows), pooled(rows)
    judged = pooled([row for row in rows if row["gate_judged"]])
    summary = {
        **provenance("examples/paper/student_summary.py", argv, cfg),
        "runs": rows,
        "pooled": pools,
        "pooled_gate_judged": judged,
        "per_task": cells,
    }
    out = Path(cfg.out)
    atomic_write(out.with_suffix(".json"), json.dumps(summary, indent=1))
    table = markdown(rows, pools, judged, cells, cfg.gate)
    atomic_write(out.with_suffix(".md"), table)
    gains = [
        {
            "task": f"{row['backbone'].upper()} {row['task']} s{row['seed']}",
            "ceiling": [row["honest_gain"]],
            "offline": [row["student_gain"]],
            "test": [row["test"]["student"] - row["test"]["base"] if row["test"] else float("nan")],
        }
        for row in rows
    ]
    methods = (("ceiling", "honest ceiling"), ("offline", "student offline"), ("test", "student on test episodes"))
    plot_metric_by_task(gains, out.with_suffix(".png"), "gain over the base policy (points)", "", methods, scale=100)
    print(table)
    return summary


if __name__ == "__main__":
    main(sys.argv[1:])
