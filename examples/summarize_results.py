"""Gathers the main job's results over tasks and seeds into tables and plots.

    python examples/summarize_results.py out=outputs/pipeline
    python examples/summarize_results.py out=outputs/pipeline trusted_json=docs/results/trusted_selection.json

Reads every ``<out>/results/<task>/<policy>_seed<seed><variant>/results.json`` and writes
``<out>/summary.md``, ``<out>/summary.json`` and ``<out>/summary_<policy>.png``: per task, backbone and
world-model variant (``paper``, or what the run changed, e.g. ``frozen+explore``),
base-policy and DALI-R success as mean +- std over seeds (population std), the difference, and
an episode-paired sign test over all seeds' episodes (how many episodes only one method solved).

Where the runs also evaluated DALI-R with the paper's arg-max and the random-candidate control
(the main job's default ``eval_methods``), it writes the trusted-selection table too
(``<out>/trusted_selection.md``, ``.json`` and ``trusted_selection_<policy>.png``): base, the
calibrated default rule, arg-max and random per task, the default's gain and its sign test.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from statistics import mean, pstdev

from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.compare import METHODS, paired_sign_test
from torchrl_dalir.evaluation.paper import TABLE1, TABLE1_TASKS
from torchrl_dalir.evaluation.plots import plot_success_by_task
from torchrl_dalir.utils import atomic_write

PAPER = "paper"  # the paper's world model and data (no variant)
TRUSTED = (("base", "base policy"), ("dalir", "DALI-R, calibrated rule"), ("argmax", "DALI-R, arg-max (paper)"), ("random", "random candidate"))


@dataclass
class Config:
    out: str = "outputs/pipeline"
    trusted_json: str | None = None  # also write the trusted-selection data here (e.g. docs/results/trusted_selection.json)
    variant: str = PAPER  # the world-model variant of the trusted-selection table and Table 1 (e.g. frozen+explore)
    table1_json: str | None = None  # also build the paper's Table 1 and write its data here (e.g. docs/results/table1.json)


def variant_label(run_name: str, policy: str, seed: int) -> str:
    """The world-model variant of a run folder ``<policy>_seed<seed><variant>``, with the seed
    taken out of the datasets it names (``fm_seed0_frozen+explore_fm_seed0`` -> ``frozen+explore``),
    so that the seeds of one variant group together; ``paper`` for none."""
    own = f"_{policy}_seed{seed}"
    return run_name.removeprefix(own[1:]).replace(own, "").lstrip("_") or PAPER


def gather(root: Path) -> list[dict]:
    """One row per (task, policy, world-model variant): per method (short name) the per-seed success
    rates and every seed's per-episode successes; the run folder and DALI-R rule of each seed; and
    the sign test of DALI-R against the base policy."""
    groups = defaultdict(lambda: {"seeds": [], "runs": [], "episodes": set(), "rules": [], "episode_success": defaultdict(list),
                                  **{m: [] for m in METHODS}})
    for path in sorted(root.glob("results/*/*/results.json")):
        result = json.loads(path.read_text())
        if not {METHODS["base"], METHODS["dalir"]} <= set(result["success"]):
            continue  # a run of some methods only (Table 3's variants: the arg-max alone) has its own table
        cfg = result["config"]
        run = path.parent.name
        group = groups[(cfg["task"], cfg["policy"], variant_label(run, cfg["policy"], cfg["seed"]))]
        group["seeds"].append(cfg["seed"])
        group["runs"].append(run)
        group["episodes"].add(cfg["eval_episodes"])
        group["rules"].append(result["success"]["DALI-R"].get("selection", "argmax(state)"))
        for short, name in METHODS.items():
            if name in result["success"]:
                group[short].append(result["success"][name]["success_rate"])
                group["episode_success"][short].extend(r["success"] for r in result["success"][name]["records"])
    return [{"task": t, "policy": p, "variant": v, **g, "episodes": sorted(g["episodes"]), "episode_success": dict(g["episode_success"]),
             **paired_sign_test(g["episode_success"]["base"], g["episode_success"]["dalir"])} for (t, p, v), g in groups.items()]


def pct(values) -> str:
    return f"{100 * mean(values):.1f} +- {100 * pstdev(values):.1f}"


def summary_table(table: list[dict]) -> str:
    lines = ["| task | policy | world model | seeds | episodes per seed | base policy (%) | + DALI-R (%) | difference (points) "
             "| episodes only base / only DALI-R solved | sign-test p |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in table:
        difference = [d - b for b, d in zip(row["base"], row["dalir"])]
        lines.append(f"| {row['task']} | {row['policy']} | {row['variant']} | {len(row['seeds'])} | "
                     f"{', '.join(map(str, row['episodes']))} | {pct(row['base'])} | {pct(row['dalir'])} | {100 * mean(difference):+.1f} | "
                     f"{row['base_only']} / {row['dalir_only']} | {row['p_value']:.2f} |")
    for policy, variant in sorted({(row["policy"], row["variant"]) for row in table}):
        rows = [row for row in table if (row["policy"], row["variant"]) == (policy, variant)]
        if len(rows) > 1:  # the mean of the per-task differences; every task's episodes pooled for the test
            test = paired_sign_test(*(sum((row["episode_success"][m] for row in rows), []) for m in ("base", "dalir")))
            difference = mean(mean(d - b for b, d in zip(row["base"], row["dalir"])) for row in rows)
            lines.append(f"| all {len(rows)} tasks | {policy} | {variant} | | | | | {100 * difference:+.1f} | "
                         f"{test['base_only']} / {test['dalir_only']} | {test['p_value']:.2f} |")
    return "\n".join(lines) + "\n"


def trusted_rows(table: list[dict], policy: str, variant: str) -> list[dict]:
    """The rows of ``policy`` and world-model ``variant`` whose every seed evaluated all four methods."""
    return [row for row in table if row["policy"] == policy and row["variant"] == variant
            and all(len(row[m]) == len(row["seeds"]) for m, _ in TRUSTED)]


def validation_rates(root: Path, task: str, seeds: list[int], runs: list[str]) -> dict:
    """Each seed's calibration on validation episodes: base and every grid entry's success (%)."""
    out = {}
    for seed, run in zip(seeds, runs):
        path = root / "calibration" / task / run / "calibration.json"
        record = json.loads(path.read_text()) if path.exists() else None
        if record and record.get("entries"):
            out[str(seed)] = {"episodes": record["episodes"], "seed": record["seed"], "base": round(100 * record["base_success_rate"], 1),
                              **{e["name"]: round(100 * e["success_rate"], 1) for e in record["entries"]}}
    return out


def trusted_selection(table: list[dict], root: Path, variant: str = PAPER) -> dict:
    """The trusted-selection data of world-model ``variant``: per backbone (``fm`` at the top
    level, others under their name) and task, the mean success (%) of every method, seeds, episodes per seed and the default's
    sign test against the base policy; the default rule (the rule family that calibration chose
    from, with each seed's setting under ``rules``) and the mean gain over the tasks."""
    out = {}
    for policy in sorted({row["policy"] for row in table}):
        rows = trusted_rows(table, policy, variant)
        if not rows:
            continue
        tasks = {row["task"]: {"base": 100 * mean(row["base"]), "default": 100 * mean(row["dalir"]), "argmax": 100 * mean(row["argmax"]),
                               "random": 100 * mean(row["random"]), "seeds": len(row["seeds"]),
                               "episodes": row["episodes"][0] if len(row["episodes"]) == 1 else row["episodes"],
                               "p_default_vs_base": row["p_value"], "only_base": row["base_only"], "only_default": row["dalir_only"],
                               "rules": dict(zip(map(str, row["seeds"]), row["rules"])),
                               "validation": validation_rates(root, row["task"], row["seeds"], row["runs"])} for row in rows}
        families = sorted({rule.split("(")[0] for t in tasks.values() for rule in t["rules"].values()})
        block = {"variant": variant, "tasks": {task: {k: round(v, 4 if k.startswith("p_") else 1) if isinstance(v, float) else v for k, v in t.items()}
                           for task, t in tasks.items()},
                 "default_rule": " / ".join(families),
                 "mean_gain": round(mean(t["default"] - t["base"] for t in tasks.values()), 1),
                 "mean_gain_argmax": round(mean(t["argmax"] - t["base"] for t in tasks.values()), 1)}
        if policy == "fm":
            out.update(block)
        else:
            out[policy] = block
    return out


def trusted_table(data: dict) -> str:
    lines = ["| backbone | task | seeds x episodes | base (%) | default rule (%) | arg-max (%) | random (%) | only base / only default | p |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for policy, block in [("fm", data), *((k, v) for k, v in data.items() if isinstance(v, dict) and "tasks" in v)]:
        if "tasks" not in block:
            continue
        for task, t in block["tasks"].items():
            lines.append(f"| {policy} | {task} | {t['seeds']} x {t['episodes']} | {t['base']:.1f} | {t['default']:.1f} | {t['argmax']:.1f} | "
                         f"{t['random']:.1f} | {t['only_base']} / {t['only_default']} | {t['p_default_vs_base']:.3f} |")
        lines.append(f"| {policy} | mean gain over base (points) | | | {block['mean_gain']:+.1f} | {block['mean_gain_argmax']:+.1f} | | | |")
    return "\n".join(lines) + "\n"


def table1(table: list[dict], variant: str = PAPER) -> dict:
    """``{backbone: {task: {"base": [% per seed], "dalir": [...], "seeds", "episodes", "p",
    "rules", "paper_base", "paper_dalir"}}}`` for the paper's six tasks that have runs of ``variant``."""
    out = {}
    for row in sorted(table, key=lambda r: (r["policy"], TABLE1_TASKS.index(r["task"]) if r["task"] in TABLE1_TASKS else len(TABLE1_TASKS))):
        if row["variant"] != variant or row["task"] not in TABLE1_TASKS:
            continue
        paper = TABLE1.get(row["policy"], {}).get(row["task"], (None, None))
        out.setdefault(row["policy"], {})[row["task"]] = {
            "base": [round(100 * r, 1) for r in row["base"]], "dalir": [round(100 * r, 1) for r in row["dalir"]],
            "seeds": row["seeds"], "episodes": row["episodes"][0] if len(row["episodes"]) == 1 else row["episodes"],
            "p": round(row["p_value"], 4), "rules": sorted(set(row["rules"])), "paper_base": paper[0], "paper_dalir": paper[1]}
    return out


def table1_markdown(data: dict) -> str:
    def cell(values):
        return f"{mean(values):.1f} +- {pstdev(values):.1f}"

    lines = ["| backbone | task | seeds x episodes | base (%) | + DALI-R (%) | gain | sign-test p | DALI-R rule | paper: base -> DALI-R |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for backbone, tasks in data.items():
        for task, t in tasks.items():
            paper = f"{t['paper_base']} -> {t['paper_dalir']}" if t["paper_base"] is not None else ""
            lines.append(f"| {backbone} | {task} | {len(t['seeds'])} x {t['episodes']} | {cell(t['base'])} | {cell(t['dalir'])} | "
                         f"{mean(t['dalir']) - mean(t['base']):+.1f} | {t['p']:.3f} | {', '.join(t['rules'])} | {paper} |")
        gains = [mean(t["dalir"]) - mean(t["base"]) for t in tasks.values()]
        papers = [t["paper_dalir"] - t["paper_base"] for t in tasks.values() if t["paper_base"] is not None]
        lines.append(f"| {backbone} | average of {len(tasks)} tasks | | {mean(mean(t['base']) for t in tasks.values()):.1f} | "
                     f"{mean(mean(t['dalir']) for t in tasks.values()):.1f} | {mean(gains):+.1f} | | | "
                     f"{f'gain {mean(papers):+.1f} on the same tasks' if papers else ''} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    root = Path(cfg.out)
    table = gather(root)
    if not table:
        raise FileNotFoundError(f"no results under {root / 'results'}; run examples/train_dp3_wm.py first")
    text = summary_table(table)
    print(text)
    atomic_write(root / "summary.md", text)
    atomic_write(root / "summary.json", json.dumps(table, indent=1))
    for policy in sorted({row["policy"] for row in table}):
        rows = [row for row in table if row["policy"] == policy and row["variant"] == cfg.variant]
        if rows:
            plot_success_by_task(rows, root / f"summary_{policy}.png", title=f"DALI-R on a frozen {policy.upper()} policy")
    trusted = trusted_selection(table, root, cfg.variant)
    if trusted:
        text = trusted_table(trusted)
        print(text)
        atomic_write(root / "trusted_selection.md", text)
        for path in [root / "trusted_selection.json", *([Path(cfg.trusted_json)] if cfg.trusted_json else [])]:
            atomic_write(path, json.dumps(trusted, indent=1) + "\n")
        for policy in sorted({row["policy"] for row in table}):
            rows = trusted_rows(table, policy, cfg.variant)
            if rows:
                plot_success_by_task(rows, root / f"trusted_selection_{policy}.png", title=f"Selection rules on a frozen {policy.upper()} policy", methods=TRUSTED)
    if cfg.table1_json:
        data = table1(table, cfg.variant)
        if not data:
            raise FileNotFoundError(f"no runs of variant {cfg.variant!r} on the paper's tasks {TABLE1_TASKS} under {root / 'results'}")
        text = table1_markdown(data)
        print(text)
        atomic_write(root / "table1.md", text)
        for path in (root / "table1.json", Path(cfg.table1_json)):
            atomic_write(path, json.dumps(data, indent=1) + "\n")
        for backbone in data:
            rows = [{"task": task, "base": [v / 100 for v in t["base"]], "dalir": [v / 100 for v in t["dalir"]]} for task, t in data[backbone].items()]
            plot_success_by_task(rows, root / f"table1_{backbone}.png", title=f"Table 1 ({backbone.upper()}): base policy and DALI-R")


if __name__ == "__main__":
    main(sys.argv[1:])
