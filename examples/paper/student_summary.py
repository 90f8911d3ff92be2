"""The distilled student over every run: its honest ceiling, its offline gain, its screen and its test, in one table.

    python examples/paper/student_summary.py          # docs/results/student_summary.{json,md,png}

Reads each run's committed results in ``results`` (a run is ``<backbone>_<task>_s<seed>``, named by its screen,
``student_screen_<run>.json``): the scorer ladder (the ``benchmarks`` of every ``scorer_benchmark*.json``: the
honest ceiling, the student's out-of-fold AUC and offline gain), the validation screen and, for a run whose screen
passed, the test (``student_test_<run>.json``). Pools the test episodes per backbone: the mean gain over the tested
runs, the paired sign test over all their episodes, and Table 1's mean: per task, the mean gain over its seeds,
where a run whose screen failed counts as gain 0 (the preregistered rule), then the mean over tasks. A run that
passed and has no test yet is left out of both means. Every number comes from those files; nothing is run.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from torchrl_dalir.branching.outcome_noise import honest_ceiling
from torchrl_dalir.branching.scorer_benchmark import all_draws, load_benchmark
from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.compare import BASE, sign_test
from torchrl_dalir.evaluation.plots import plot_metric_by_task
from torchrl_dalir.utils import atomic_write, provenance

ROOT = Path(__file__).resolve().parents[2]
STUDENT = "critic"  # critic_screen.py's name of the reranked method


@dataclass
class Config:
    results: str = str(ROOT / "docs" / "results")  # the committed result files
    benchmarks: str = str(ROOT / "benchmarks" / "scorer")  # the runs' benchmark files (the ceiling's standard error)
    out: str = str(ROOT / "docs" / "results" / "student_summary")  # <out>.json, <out>.md and <out>.png


def episodes(path: Path) -> dict:
    """A screen's or test's base and student success rates, paired counts and episodes."""
    result = json.loads(path.read_text())
    methods, paired = result["methods"], result["paired"]
    return {
        "episodes": methods[BASE]["episodes"],
        "base": methods[BASE]["success_rate"],
        "student": methods[STUDENT]["success_rate"],
        "won": paired["dalir_only"],
        "lost": paired["base_only"],
        "p_value": paired["p_value"],
    }


def run_rows(results: Path, benchmarks: Path) -> list[dict]:
    """One row per screened run: the ladder's rungs (the honest ceiling's standard error over decisions from the
    run's benchmark file), the screen and, where it exists, the test."""
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
        screened = episodes(screen)
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
                "passed": screened["won"] > screened["lost"],
                "test": episodes(test) if test.exists() else None,
            }
        )
    return rows


def test_gain(row: dict) -> float | None:
    """A run's test gain for Table 1: the student's minus the base policy's success rate; 0 where the screen
    failed (no test episode is run); None where the screen passed and the test has not run yet."""
    if row["test"]:
        return row["test"]["student"] - row["test"]["base"]
    return None if row["passed"] else 0.0


def pooled(rows: list[dict], cells: list[dict]) -> dict:
    """Per backbone: over the runs with a test, the mean gain (points), wins, losses and the sign test; Table 1's
    mean, over the backbone's tasks of each task's mean over its seeds (:func:`per_task`, a failed screen counts
    0), as ``table1_gain`` over ``table1_tasks`` tasks of ``table1_runs`` runs."""
    table = {}
    for backbone in sorted({row["backbone"] for row in rows}):
        tests = [row["test"] for row in rows if row["backbone"] == backbone and row["test"]]
        tasks = [cell for cell in cells if cell["backbone"] == backbone]
        if tasks:
            won, lost = sum(t["won"] for t in tests), sum(t["lost"] for t in tests)
            gain = sum(t["student"] - t["base"] for t in tests) / len(tests) if tests else float("nan")
            table[backbone] = {
                "runs": len(tests),
                "mean_gain": gain,
                **sign_test(lost, won),
                "table1_tasks": len(tasks),
                "table1_runs": sum(len(cell["seeds"]) for cell in tasks),
                "table1_gain": sum(cell["mean_gain"] for cell in tasks) / len(tasks),
            }
    return table


def per_task(rows: list[dict]) -> list[dict]:
    """Table 1's cells: per backbone and task, the seeds with a Table 1 gain and its mean over them."""
    cells = {}
    for row in rows:
        if (gain := test_gain(row)) is not None:
            cells.setdefault((row["backbone"], row["task"]), {})[row["seed"]] = gain
    return [
        {"backbone": backbone, "task": task, "seeds": sorted(gains), "mean_gain": sum(gains.values()) / len(gains)}
        for (backbone, task), gains in sorted(cells.items())
    ]


def markdown(rows: list[dict], pools: dict, cells: list[dict]) -> str:
    lines = [
        "| run | split decisions | honest ceiling (± SE) | student offline: AUC / gain "
        "| validation: base -> student (won / lost) | test: base -> student (won / lost, p) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        screen, test = row["screen"], row["test"]
        tested = (
            f"{100 * test['base']:.0f} -> {100 * test['student']:.0f} % ({test['won']} / {test['lost']}, "
            f"p = {test['p_value']:.2g})"
            if test
            else ("not run yet" if row["passed"] else "not run (screen failed)")
        )
        lines.append(
            f"| {row['run']} | {row['split_decisions']} | "
            f"{100 * row['honest_gain']:+.1f} ± {100 * row['honest_gain_se']:.1f} | "
            f"{row['student_auc']:.2f} / {100 * row['student_gain']:+.1f} | {100 * screen['base']:.0f} -> "
            f"{100 * screen['student']:.0f} % ({screen['won']} / {screen['lost']}) | {tested} |"
        )
    for backbone, pool in pools.items():
        lines.append(
            f"\n{backbone.upper()}: {pool['runs']} tested runs, mean test gain {100 * pool['mean_gain']:+.1f} points, "
            f"{pool['dalir_only']} won / {pool['base_only']} lost (sign test p = {pool['p_value']:.2g}); "
            f"Table 1's mean over {pool['table1_tasks']} tasks ({pool['table1_runs']} screened runs; a failed screen "
            f"counts 0): {100 * pool['table1_gain']:+.1f} points."
        )
    lines += ["", "| backbone | task | seeds | mean test gain (failed screen = 0) |", "| --- | --- | --- | --- |"]
    for cell in cells:
        seeds = ", ".join(str(seed) for seed in cell["seeds"])
        lines.append(f"| {cell['backbone'].upper()} | {cell['task']} | {seeds} | {100 * cell['mean_gain']:+.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    rows = run_rows(Path(cfg.results), Path(cfg.benchmarks))
    if not rows:
        raise FileNotFoundError(f"no student_screen_<run>.json in {cfg.results}: screen a student first")
    cells = per_task(rows)
    pools = pooled(rows, cells)
    summary = {
        **provenance("examples/paper/student_summary.py", argv, cfg),
        "runs": rows,
        "pooled": pools,
        "per_task": cells,
    }
    out = Path(cfg.out)
    atomic_write(out.with_suffix(".json"), json.dumps(summary, indent=1))
    table = markdown(rows, pools, cells)
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
