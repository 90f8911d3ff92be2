"""Gathers the main job's results over tasks and seeds into tables and plots.

    python examples/paper/summarize_results.py out=outputs/pipeline
    python examples/paper/summarize_results.py out=outputs/pipeline trusted_json=docs/results/trusted_selection.json
    python examples/paper/summarize_results.py out=outputs/pipeline save_records=docs/results/runs  # keep the records
    python examples/paper/summarize_results.py out=outputs/tables records=[docs/results/runs] variant=frozen+explore
    python examples/paper/summarize_results.py ... table1_json=docs/results/table1.json readme=README.md  # + tables

Reads every run of the main job under ``out`` (``<out>/results/<task>/<run>/results.json`` and its
calibration) and the committed run records under ``records`` (:mod:`torchrl_dalir.pipeline.records`:
one small JSON per run, which adds up across sessions and machines; ``save_records`` writes the
runs under ``out`` as such records), and writes ``<out>/summary.md``, ``<out>/summary.json`` and
``<out>/summary_<policy>.png``: per task, backbone and world-model variant (``paper``, or what the
run changed, e.g. ``frozen+explore``), base-policy and DALI-R success as mean +- std over seeds
(population std), the difference, and an episode-paired sign test over all seeds' episodes (how
many episodes only one method solved).

Where the runs also evaluated DALI-R with the paper's arg-max and the random-candidate control
(the main job's default ``eval_methods``), it writes the trusted-selection table too
(``<out>/trusted_selection.md``, ``.json`` and ``trusted_selection_<policy>.png``): base, the
calibrated default rule, arg-max and random per task (``tasks`` restricts it), the default's gain
and its sign test.

Runs that logged their stages (``<out>/stages/``, kept in their records) also give
``<out>/run_costs.md``: each run's wall time per stage and its peak memory.

``table1_json`` builds the paper's Table 1 (markdown, JSON and a bar plot per backbone, the plots
also next to the JSON); ``readme`` rewrites the tables between the file's ``<!-- table 1 -->`` /
``<!-- trusted-selection table -->`` markers and their ``<!-- end ... -->``, keeping each region's
first paragraph (its caption, written by hand); a table whose marker the file does not hold is left
out of it. ``examples/maintainer/update_readme_tables.py`` rebuilds the committed tables from the run
records and rewrites them in ``README.md`` and ``docs/results/README.md``.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from statistics import mean, pstdev

from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.compare import METHODS, sign_test
from torchrl_dalir.evaluation.paper import TABLE1, TABLE1_TASKS
from torchrl_dalir.evaluation.plots import plot_success_by_task
from torchrl_dalir.pipeline import STAGES
from torchrl_dalir.pipeline.records import (
    DEFAULT_VARIANT,
    PAPER,
    discordant,
    load_records,
    merge_records,
    records_from_runs,
    save_records,
)
from torchrl_dalir.utils import atomic_write

TRUSTED = (
    ("base", "base policy"),
    ("dalir", "DALI-R, calibrated rule"),
    ("argmax", "DALI-R, arg-max (paper)"),
    ("random", "random candidate"),
)


@dataclass
class Config:
    out: str = "outputs/pipeline"
    records: list[str] = field(default_factory=list)  # folders of committed run records, e.g. [docs/results/runs]
    save_records: str | None = None  # write a record of every run under out here (e.g. docs/results/runs)
    run_commit: str | None = None  # the commit that made the runs under out, for results that do not name it
    trusted_json: str | None = (
        None  # also write the trusted-selection data here (e.g. docs/results/trusted_selection.json)
    )
    # the world-model variant of the trusted-selection table and Table 1 (paper: the paper's world model)
    variant: str = DEFAULT_VARIANT
    tasks: list[str] = field(default_factory=list)  # the trusted-selection table's tasks (all if empty)
    table1_json: str | None = (
        None  # also build the paper's Table 1 and write its data here (e.g. docs/results/table1.json)
    )
    readme: str | None = None  # rewrite the generated tables in this markdown file (e.g. README.md)


def cost_table(records: list[dict]) -> str:
    """Each run's wall time per stage (minutes; the attempt that finished the stage) and peak
    memory (main process / largest collector worker), for the records that kept them; empty if
    none did."""
    timed = sorted(
        (r for r in records if r.get("stage_seconds")), key=lambda r: (r["policy"], r["task"], r["variant"], r["seed"])
    )
    if not timed:
        return ""
    lines = [
        (
            f"| backbone | task | variant | seed | {' | '.join(STAGES)} | total (min) "
            "| peak memory, main / workers (GiB) |"
        ),
        "| --- | --- | --- | --- |" + " --- |" * (len(STAGES) + 2),
    ]
    for r in timed:
        minutes = [r["stage_seconds"].get(s) for s in STAGES]
        cells = " | ".join("" if m is None else f"{m / 60:.1f}" for m in minutes)
        lines.append(
            f"| {r['policy']} | {r['task']} | {r['variant']} | {r['seed']} | {cells} | "
            f"{sum(m for m in minutes if m is not None) / 60:.1f} | "
            f"{r.get('peak_memory_gib')} / {r.get('workers_peak_memory_gib')} |"
        )
    lines.append(
        "\nA blank stage was not run by that job (it ran earlier, or another job sharing the folder ran it: "
        "the demos of a task serve every seed), so totals compare only between runs that ran the same stages."
    )
    return "\n".join(lines) + "\n"


def replace_region(text: str, marker: str, generated: str) -> str:
    """``text`` with the part between ``<!-- marker -->`` and ``<!-- end marker -->`` replaced by its
    first paragraph (the caption written by hand) and ``generated``."""
    start, end = f"<!-- {marker} -->", f"<!-- end {marker} -->"
    if text.count(start) != 1 or text.count(end) != 1 or text.index(start) > text.index(end):
        raise ValueError(f"expected one {start} before one {end}")
    i, j = text.index(start) + len(start), text.index(end)
    region = text[i:j]
    caption = region.strip("\n").split("\n\n")[0]
    if "\n\n" not in region.strip("\n") or caption.lstrip().startswith("|"):
        raise ValueError(
            f"the text after {start} must start with a caption paragraph, then a blank line, then the table"
        )
    body, tail = generated.strip("\n"), region[len(region.rstrip("\n")) :]
    return f"{text[:i]}\n{caption}\n\n{body}{tail}{text[j:]}"


def gather(records: list[dict]) -> list[dict]:
    """One row per (task, policy, world-model variant): per method (short name) the per-seed success
    rates and the test episodes only the base policy / only that method solved, summed over seeds
    (``discordant``); each seed's run, DALI-R rule and calibration on validation episodes; and the
    sign test of DALI-R against the base policy."""
    groups = defaultdict(
        lambda: {
            "seeds": [],
            "runs": [],
            "episodes": set(),
            "rules": [],
            "validation": {},
            "discordant": defaultdict(lambda: [0, 0]),
            "argmax_vs_random": [0, 0, 0],
            **{m: [] for m in METHODS},
        }
    )
    for record in sorted(records, key=lambda r: (r["task"], r["policy"], r["variant"], r["seed"])):
        group = groups[(record["task"], record["policy"], record["variant"])]
        group["seeds"].append(record["seed"])
        group["runs"].append(record["run"])
        group["episodes"].add(record["episodes"])
        group["rules"].append(record["methods"]["dalir"].get("selection", "argmax(state)"))
        if "validation" in record:
            group["validation"][str(record["seed"])] = validation_rates(record["validation"])
        for short, row in record["methods"].items():
            group[short].append(row["success_rate"])
            if short != "base":
                counts = group["discordant"][short]
                counts[0], counts[1] = (a + b for a, b in zip(counts, discordant(record, short)))
        # the scorer's pick against a random pick among the same candidates, where both kept their episodes
        pair = (
            discordant(record, "argmax", against="random") if {"argmax", "random"} <= set(record["methods"]) else None
        )
        if pair is not None:
            group["argmax_vs_random"] = [a + b for a, b in zip(group["argmax_vs_random"], (*pair, 1))]
    return [
        {
            "task": t,
            "policy": p,
            "variant": v,
            **g,
            "episodes": sorted(g["episodes"]),
            "discordant": dict(g["discordant"]),
            **sign_test(*g["discordant"]["dalir"]),
        }
        for (t, p, v), g in groups.items()
    ]


def validation_rates(validation: dict) -> dict:
    """A seed's calibration on validation episodes: base and every grid entry's success (%) (with
    ``design=failures``, each entry's screen), and the confirmation of the chosen entry on fresh
    validation episodes if there was one."""
    rates = {"episodes": validation["episodes"], "seed": validation["seed"], "base": round(100 * validation["base"], 1)}
    if (
        validation.get("design") == "failures"
    ):  # screened on the base policy's failures: each entry's wins, losses and estimated gain
        rates.update(design="failures", failed=validation["failed"], **validation["entries"])
    else:
        rates.update({name: round(100 * e["success_rate"], 1) for name, e in validation["entries"].items()})
    confirmation = validation.get("confirmation")
    if confirmation:
        rates["confirmation"] = {
            **confirmation,
            "base": round(100 * confirmation["base"], 1),
            "success_rate": round(100 * confirmation["success_rate"], 1),
        }
    return rates


def pct(values) -> str:
    return f"{100 * mean(values):.1f} +- {100 * pstdev(values):.1f}"


def summary_table(table: list[dict]) -> str:
    lines = [
        (
            "| task | policy | world model | seeds | episodes per seed | base policy (%) | + DALI-R (%) "
            "| difference (points) | episodes only base / only DALI-R solved | sign-test p |"
        ),
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in table:
        difference = [d - b for b, d in zip(row["base"], row["dalir"])]
        lines.append(
            f"| {row['task']} | {row['policy']} | {row['variant']} | {len(row['seeds'])} | "
            f"{', '.join(map(str, row['episodes']))} | {pct(row['base'])} | {pct(row['dalir'])} | "
            f"{100 * mean(difference):+.1f} | "
            f"{row['base_only']} / {row['dalir_only']} | {row['p_value']:.2f} |"
        )
    for policy, variant in sorted({(row["policy"], row["variant"]) for row in table}):
        rows = [row for row in table if (row["policy"], row["variant"]) == (policy, variant)]
        if len(rows) > 1:  # the mean of the per-task differences; every task's episodes pooled for the test
            test = sign_test(*(sum(row["discordant"]["dalir"][i] for row in rows) for i in (0, 1)))
            difference = mean(mean(d - b for b, d in zip(row["base"], row["dalir"])) for row in rows)
            lines.append(
                f"| all {len(rows)} tasks | {policy} | {variant} | | | | | {100 * difference:+.1f} | "
                f"{test['base_only']} / {test['dalir_only']} | {test['p_value']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def trusted_rows(table: list[dict], policy: str, variant: str, tasks: list[str] | None = None) -> list[dict]:
    """The rows of ``policy``, world-model ``variant`` and ``tasks`` (all if empty) whose every seed evaluated
    all four methods."""
    return [
        row
        for row in table
        if row["policy"] == policy
        and row["variant"] == variant
        and (not tasks or row["task"] in tasks)
        and all(len(row[m]) == len(row["seeds"]) for m, _ in TRUSTED)
    ]


def trusted_selection(table: list[dict], variant: str = PAPER, tasks: list[str] | None = None) -> dict:
    """The trusted-selection data of world-model ``variant`` on ``tasks`` (all if empty): per
    backbone (``fm`` at the top level, others under their name) and task, the mean success (%) of
    every method, seeds, episodes per seed, the default's sign test against the base policy
    (``p_default_vs_base``, ``only_base``, ``only_default``) and the arg-max's and the random pick's
    (``argmax_vs_base``, ``random_vs_base``), the arg-max against the random pick
    (:func:`argmax_vs_random`), each seed's rule and validation results; the default rule (the
    rule families that calibration chose from), the mean gain over the tasks of the default, the
    arg-max and the random pick, and the arg-max against the random pick over every task."""
    out = {}
    for policy in sorted({row["policy"] for row in table}):
        rows = trusted_rows(table, policy, variant, tasks)
        if not rows:
            continue
        per_task = {
            row["task"]: {
                "base": 100 * mean(row["base"]),
                "default": 100 * mean(row["dalir"]),
                "argmax": 100 * mean(row["argmax"]),
                "random": 100 * mean(row["random"]),
                "seeds": len(row["seeds"]),
                "episodes": row["episodes"][0] if len(row["episodes"]) == 1 else row["episodes"],
                "p_default_vs_base": row["p_value"],
                "only_base": row["base_only"],
                "only_default": row["dalir_only"],
                **{f"{m}_vs_base": sign_test(*row["discordant"][m]) for m in ("argmax", "random")},
                "argmax_vs_random": argmax_vs_random([row]),
                "rules": dict(zip(map(str, row["seeds"]), row["rules"])),
                "validation": row["validation"],
            }
            for row in rows
        }
        families = sorted({rule.split("(")[0] for t in per_task.values() for rule in t["rules"].values()})
        block = {
            "variant": variant,
            "tasks": {
                task: {k: round(v, 4 if k.startswith("p_") else 1) if isinstance(v, float) else v for k, v in t.items()}
                for task, t in per_task.items()
            },
            "default_rule": " / ".join(families),
            "mean_gain": round(mean(t["default"] - t["base"] for t in per_task.values()), 1),
            "mean_gain_argmax": round(mean(t["argmax"] - t["base"] for t in per_task.values()), 1),
            "mean_gain_random": round(mean(t["random"] - t["base"] for t in per_task.values()), 1),
            "argmax_vs_random": argmax_vs_random(rows),
        }
        if policy == "fm":
            out.update(block)
        else:
            out[policy] = block
    return out


def argmax_vs_random(rows: list[dict]) -> dict:
    """The paper's arg-max against a random pick among the same candidates, pooled over the runs of
    ``rows`` that kept both methods' per-episode outcomes: the test episodes only the random pick /
    only the arg-max solved, and the two-sided sign test (is the scorer's choice better than chance?)."""
    random_only, argmax_only, runs = (sum(row["argmax_vs_random"][i] for row in rows) for i in range(3))
    test = sign_test(random_only, argmax_only)
    return {"runs": runs, "random_only": random_only, "argmax_only": argmax_only, "p_value": round(test["p_value"], 4)}


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def trusted_table(data: dict) -> str:
    lines = [
        (
            "| backbone | task | seeds x episodes | base (%) | default rule (%) | only base / only default | p "
            "| arg-max (%) | only base / only arg-max | random (%) | only base / only random |"
        ),
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for policy, block in [("fm", data), *((k, v) for k, v in data.items() if isinstance(v, dict) and "tasks" in v)]:
        if "tasks" not in block:
            continue
        for task, t in block["tasks"].items():
            pair = {
                m: (
                    f"{t[f'{m}_vs_base']['base_only']} / {t[f'{m}_vs_base']['dalir_only']} "
                    f"(p = {t[f'{m}_vs_base']['p_value']:.2f})"
                )
                for m in ("argmax", "random")
            }
            lines.append(
                f"| {policy} | {task} | {t['seeds']} x {t['episodes']} | {t['base']:.1f} | {t['default']:.1f} | "
                f"{t['only_base']} / {t['only_default']} | {t['p_default_vs_base']:.3f} | "
                f"{t['argmax']:.1f} | {pair['argmax']} | "
                f"{t['random']:.1f} | {pair['random']} |"
            )
        lines.append(
            f"| {policy} | mean gain over base (points) | | | {block['mean_gain']:+.1f} | | | "
            f"{block['mean_gain_argmax']:+.1f} | | "
            f"{block['mean_gain_random']:+.1f} | |"
        )
    for policy, block in [("fm", data), *((k, v) for k, v in data.items() if isinstance(v, dict) and "tasks" in v)]:
        if block.get("argmax_vs_random", {}).get("runs"):
            pair = block["argmax_vs_random"]
            lines.append(
                f"\n{policy}: the arg-max against a random pick among the same candidates, "
                f"over the {_count(pair['runs'], 'run')} that kept both methods' episodes: "
                f"only the arg-max {pair['argmax_only']}, only the random pick {pair['random_only']} "
                f"(two-sided sign test p = {pair['p_value']:.3f})."
            )
    return "\n".join(lines) + "\n"


def table1(table: list[dict], variant: str = PAPER) -> dict:
    """``{backbone: {task: {"base": [% per seed], "dalir": [...], "seeds", "episodes", "p",
    "rules", "paper_base", "paper_dalir"}}}`` for the paper's six tasks that have runs of ``variant``."""
    out = {}
    for row in sorted(
        table,
        key=lambda r: (r["policy"], TABLE1_TASKS.index(r["task"]) if r["task"] in TABLE1_TASKS else len(TABLE1_TASKS)),
    ):
        if row["variant"] != variant or row["task"] not in TABLE1_TASKS:
            continue
        paper = TABLE1.get(row["policy"], {}).get(row["task"], (None, None))
        out.setdefault(row["policy"], {})[row["task"]] = {
            "base": [round(100 * r, 1) for r in row["base"]],
            "dalir": [round(100 * r, 1) for r in row["dalir"]],
            "seeds": row["seeds"],
            "episodes": row["episodes"][0] if len(row["episodes"]) == 1 else row["episodes"],
            "p": round(row["p_value"], 4),
            "rules": sorted(set(row["rules"])),
            "paper_base": paper[0],
            "paper_dalir": paper[1],
        }
    return out


def table1_markdown(data: dict) -> str:
    def cell(values):
        return f"{mean(values):.1f} +- {pstdev(values):.1f}"

    lines = [
        (
            "| backbone | task | seeds x episodes | base (%) | + DALI-R (%) | gain | sign-test p | DALI-R rule "
            "| paper: base -> DALI-R |"
        ),
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for backbone, tasks in data.items():
        for task, t in tasks.items():
            paper = f"{t['paper_base']} -> {t['paper_dalir']}" if t["paper_base"] is not None else ""
            lines.append(
                f"| {backbone} | {task} | {len(t['seeds'])} x {t['episodes']} | "
                f"{cell(t['base'])} | {cell(t['dalir'])} | "
                f"{mean(t['dalir']) - mean(t['base']):+.1f} | {t['p']:.3f} | {', '.join(t['rules'])} | {paper} |"
            )
        gains = [mean(t["dalir"]) - mean(t["base"]) for t in tasks.values()]
        papers = [t["paper_dalir"] - t["paper_base"] for t in tasks.values() if t["paper_base"] is not None]
        lines.append(
            f"| {backbone} | average of {_count(len(tasks), 'task')} | | "
            f"{mean(mean(t['base']) for t in tasks.values()):.1f} | "
            f"{mean(mean(t['dalir']) for t in tasks.values()):.1f} | {mean(gains):+.1f} | | | "
            f"{f'gain {mean(papers):+.1f} on the same tasks' if papers else ''} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    root = Path(cfg.out)
    runs = records_from_runs(root, cfg.run_commit)
    if cfg.save_records:
        for path in save_records(runs, cfg.save_records):
            print(f"record: {path}")
    records = merge_records(runs, load_records(cfg.records))
    table = gather(records)
    if not table:
        raise FileNotFoundError(
            f"no results under {root / 'results'} nor records under {cfg.records}; run examples/train_dp3_wm.py first"
        )
    text = summary_table(table)
    print(text)
    atomic_write(root / "summary.md", text)
    atomic_write(root / "summary.json", json.dumps(table, indent=1))
    costs = cost_table(records)
    if costs:
        print(costs)
        atomic_write(root / "run_costs.md", costs)
    for policy in sorted({row["policy"] for row in table}):
        rows = [row for row in table if row["policy"] == policy and row["variant"] == cfg.variant]
        if rows:
            plot_success_by_task(
                rows, root / f"summary_{policy}.png", title=f"DALI-R on a frozen {policy.upper()} policy"
            )
    generated = {}  # README marker -> the markdown built here
    trusted = trusted_selection(table, cfg.variant, cfg.tasks)
    if trusted:
        text = generated["trusted-selection table"] = trusted_table(trusted)
        print(text)
        atomic_write(root / "trusted_selection.md", text)
        for path in [root / "trusted_selection.json", *([Path(cfg.trusted_json)] if cfg.trusted_json else [])]:
            atomic_write(path, json.dumps(trusted, indent=1) + "\n")
        for policy in sorted({row["policy"] for row in table}):
            rows = trusted_rows(table, policy, cfg.variant, cfg.tasks)
            if rows:
                plot_success_by_task(
                    rows,
                    root / f"trusted_selection_{policy}.png",
                    title=f"Selection rules on a frozen {policy.upper()} policy",
                    methods=TRUSTED,
                )
    if cfg.table1_json:
        data = table1(table, cfg.variant)
        if not data:
            raise FileNotFoundError(f"no runs of variant {cfg.variant!r} on the paper's tasks {TABLE1_TASKS}")
        text = generated["table 1"] = table1_markdown(data)
        print(text)
        atomic_write(root / "table1.md", text)
        for path in (root / "table1.json", Path(cfg.table1_json)):
            atomic_write(path, json.dumps(data, indent=1) + "\n")
        for backbone in data:
            rows = []
            for task, t in data[backbone].items():
                row = {"task": task}
                for key in ("base", "dalir"):
                    row[key] = [v / 100 for v in t[key]]
                    row[f"{key}_paper"] = None if t[f"paper_{key}"] is None else t[f"paper_{key}"] / 100
                rows.append(row)
            for folder in {root, Path(cfg.table1_json).parent}:
                plot_success_by_task(
                    rows,
                    folder / f"table1_{backbone}.png",
                    title=f"Table 1 ({backbone.upper()}): base policy and DALI-R (black lines: the paper)",
                )
    if cfg.readme:
        readme = Path(cfg.readme)
        text = readme.read_text(encoding="utf-8")
        for marker in ("table 1", "trusted-selection table"):
            if marker in generated and f"<!-- {marker} -->" in text:
                text = replace_region(text, marker, generated[marker])
                print(f"{readme}: the {marker} rewritten")
            elif marker in generated:
                print(f"{readme}: holds no <!-- {marker} --> marker, so the {marker} is not written there")
            elif f"<!-- {marker} -->" in text:
                print(f"{readme}: the {marker} left as it was (not built by this command)")
        atomic_write(readme, text)


if __name__ == "__main__":
    main(sys.argv[1:])
