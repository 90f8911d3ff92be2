"""Gathers ``examples/evaluate.py`` runs into one table: every method of every run, per task,
paired against the base policy on the same episodes.

    python examples/paper/summarize_evaluations.py root=outputs/screen out=docs/results/screen.json

Reads ``<root>/<task>/<run>/evaluation.json`` (one folder per task, one per evaluation run; a
run's name says what it varied, e.g. ``frozen_argmax``). In each task, the base policy's episodes
(from whichever run evaluated it) are the reference: every other method gets its success rate,
the episodes only the base policy / only the method solved, and the exact sign-test p-value
(:func:`~torchrl_dalir.evaluation.compare.paired_sign_test`). Runs of one task must share the
evaluation seed and episode count. Writes markdown next to ``out`` and prints it.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.compare import BASE, paired_sign_test
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    root: str = "outputs/screen"
    out: str = "outputs/screen/summary.json"


def gather(root: Path) -> dict:
    """``{task: {"episodes", "seed", "base", "methods": {"<run>/<method>": {...}}}}``."""
    tasks = {}
    for task_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        runs = {path.parent.name: json.loads(path.read_text()) for path in sorted(task_dir.glob("*/evaluation.json"))}
        if not runs:
            continue
        settings = {(r["config"]["seed"], r["config"]["episodes"]) for r in runs.values()}
        if len(settings) > 1:
            raise ValueError(
                f"{task_dir}: runs on different episodes {sorted(settings)}; "
                "compare runs of one evaluation seed and size"
            )
        base = next((r["success"][BASE] for r in runs.values() if BASE in r["success"]), None)
        if base is None:
            raise ValueError(f"{task_dir}: no run evaluated the base policy ({BASE!r}), so nothing to pair against")
        base_successes = [e["success"] for e in base["records"]]
        methods = {}
        for run_name, run in runs.items():
            for method, row in run["success"].items():
                if method == BASE:
                    continue
                test = paired_sign_test(base_successes, [e["success"] for e in row["records"]])
                methods[f"{run_name}/{method}"] = {
                    "selection": row.get("selection", ""),
                    "success_rate": row["success_rate"],
                    **test,
                }
        seed, episodes = settings.pop()
        tasks[task_dir.name] = {"seed": seed, "episodes": episodes, "base": base["success_rate"], "methods": methods}
    return tasks


def main(argv: list[str]) -> None:
    cfg = parse_config(Config, argv)
    tasks = gather(Path(cfg.root))
    lines = [
        "| task | run / method | rule | success | only base / only this | p |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for task, entry in tasks.items():
        lines.append(
            f"| {task} (seed {entry['seed']}, {entry['episodes']} episodes) | base policy | | {entry['base']:.1%} | | |"
        )
        for name, row in entry["methods"].items():
            lines.append(
                f"| | {name} | {row['selection']} | {row['success_rate']:.1%} "
                f"| {row['base_only']} / {row['dalir_only']} | {row['p_value']:.2f} |"
            )
    table = "\n".join(lines)
    print(table)
    out = Path(cfg.out)
    command = " ".join(["python examples/paper/summarize_evaluations.py", *argv])
    atomic_write(
        out,
        json.dumps(
            {"command": command, "runs": {t: sorted(e["methods"]) for t, e in tasks.items()}, "tasks": tasks}, indent=1
        ),
    )
    atomic_write(out.with_suffix(".md"), table + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
