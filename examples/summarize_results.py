"""Gathers the main job's results over tasks and seeds into one table and one plot.

    python examples/summarize_results.py out=outputs/pipeline

Reads every ``<out>/results/<task>/<policy>_seed<seed>[_<scorer target>]/results.json`` and writes
``<out>/summary.md``, ``<out>/summary.json`` and ``<out>/summary_<policy>.png``: per task and backbone,
base-policy and DALI-R success as mean +- std over seeds (population std), the difference, and
an episode-paired sign test over all seeds' episodes (how many episodes only one method solved).
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from statistics import mean, pstdev

from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.compare import BASE, DALIR, paired_sign_test
from torchrl_dalir.evaluation.plots import plot_success_by_task
from torchrl_dalir.utils import atomic_write_text


@dataclass
class Config:
    out: str = "outputs/pipeline"


def gather(root: Path) -> list[dict]:
    groups = defaultdict(lambda: {"base": [], "dalir": [], "seeds": [], "episodes": set(), "episode_success": {"base": [], "dalir": []}})
    for path in sorted(root.glob("results/*/*/results.json")):
        result = json.loads(path.read_text())
        cfg = result["config"]
        group = groups[(cfg["task"], cfg["policy"], cfg["world_model"].get("scorer_target", "completion"))]
        group["base"].append(result["success"][BASE]["success_rate"])
        group["dalir"].append(result["success"][DALIR]["success_rate"])
        group["seeds"].append(cfg["seed"])
        group["episodes"].add(cfg["eval_episodes"])
        for name, method in (("base", BASE), ("dalir", DALIR)):
            group["episode_success"][name].extend(r["success"] for r in result["success"][method]["records"])
    return [{"task": t, "policy": p, "scorer_target": s, **g, "episodes": sorted(g["episodes"]),
             **paired_sign_test(g["episode_success"]["base"], g["episode_success"]["dalir"])} for (t, p, s), g in groups.items()]


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    root = Path(cfg.out)
    table = gather(root)
    if not table:
        raise FileNotFoundError(f"no results under {root / 'results'}; run examples/train_dp3_wm.py first")

    def pct(values):
        return f"{100 * mean(values):.1f} +- {100 * pstdev(values):.1f}"

    lines = ["| task | policy | scorer target | seeds | episodes per seed | base policy (%) | + DALI-R (%) | difference (points) "
             "| episodes only base / only DALI-R solved | sign-test p |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in table:
        difference = [d - b for b, d in zip(row["base"], row["dalir"])]
        lines.append(f"| {row['task']} | {row['policy']} | {row['scorer_target']} | {len(row['seeds'])} | "
                     f"{', '.join(map(str, row['episodes']))} | {pct(row['base'])} | {pct(row['dalir'])} | {100 * mean(difference):+.1f} | "
                     f"{row['base_only']} / {row['dalir_only']} | {row['p_value']:.2f} |")
    for policy, target in sorted({(row["policy"], row["scorer_target"]) for row in table}):
        rows = [row for row in table if (row["policy"], row["scorer_target"]) == (policy, target)]
        if len(rows) > 1:  # the mean of the per-task differences; every task's episodes pooled for the test
            test = paired_sign_test(*(sum((row["episode_success"][m] for row in rows), []) for m in ("base", "dalir")))
            difference = mean(mean(d - b for b, d in zip(row["base"], row["dalir"])) for row in rows)
            lines.append(f"| all {len(rows)} tasks | {policy} | {target} | | | | | {100 * difference:+.1f} | "
                         f"{test['base_only']} / {test['dalir_only']} | {test['p_value']:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    atomic_write_text(root / "summary.md", text)
    atomic_write_text(root / "summary.json", json.dumps(table, indent=1))
    for policy in sorted({row["policy"] for row in table}):
        rows = [row for row in table if row["policy"] == policy and row["scorer_target"] == "completion"]
        if rows:
            plot_success_by_task(rows, root / f"summary_{policy}.png", title=f"DALI-R on a frozen {policy.upper()} policy")


if __name__ == "__main__":
    main(sys.argv[1:])
