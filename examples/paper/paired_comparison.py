"""Two methods on the same test episodes of chosen runs: per run and pooled, with the sign test.

    python examples/paper/paired_comparison.py runs=[dp/stick-pull/1,dp/stick-pull/2] method=random against=base
    python examples/paper/paired_comparison.py runs=[dp/stick-pull/2] method=dropout \\
        evaluations=[outputs/evaluation/evaluation.json] json=docs/results/<name>.json

Reads the committed run records (``records``, :mod:`torchrl_dalir.pipeline.records`) of ``runs``
(``<policy>/<task>/<seed>`` of world-model variant ``variant``) and counts, per run, the test
episodes that only ``against`` and only ``method`` solved; then pools them over the runs with the
exact two-sided sign test, and the largest net loss of one run. It reads only the runs it is
given: a question fixed before the runs (e.g. ``docs/results/dropout_pick_prereg.json``) names its
runs and methods, and its threshold is read off the counts.

``evaluations`` adds methods that the main job did not run: the ``evaluation.json`` of
``examples/evaluate.py`` on a run's checkpoints, one per run in the order of ``runs``. Each must
have run the record's test episodes with the run's own policy checkpoint
(``.../<task>/<policy>_seed<seed>/checkpoint.pt``) and ``actor_seed`` (the run's seed, as the main
job); a method the record holds too must have the record's outcomes. Prints a markdown table;
``json`` also writes the counts.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.compare import METHODS, sign_test
from torchrl_dalir.pipeline.records import DEFAULT_VARIANT, SHORT, discordant, load_records, outcome_string
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    runs: list[str] = field(default_factory=list)  # <policy>/<task>/<seed>, e.g. dp/stick-pull/1
    method: str = "random"
    against: str = "base"
    records: list[str] = field(default_factory=lambda: ["docs/results/runs"])
    variant: str = DEFAULT_VARIANT
    evaluations: list[str] = field(default_factory=list)  # examples/evaluate.py outputs, one per run
    json: str | None = None

    def __post_init__(self):
        if not self.runs:
            raise ValueError("name the runs to compare: runs=[<policy>/<task>/<seed>, ...]")
        unknown = {self.method, self.against} - set(METHODS)
        if unknown:
            raise ValueError(f"unknown methods {sorted(unknown)}; choose among {sorted(METHODS)}")
        if self.method == self.against:
            raise ValueError(f"method and against are both {self.method!r}: compare two methods")
        if len(set(self.runs)) != len(self.runs):
            raise ValueError(f"runs {self.runs} name a run twice: its episodes would count twice")
        if self.evaluations and len(self.evaluations) != len(self.runs):
            raise ValueError(
                f"{len(self.evaluations)} evaluations for {len(self.runs)} runs: give one per run, in order"
            )


def with_evaluation(record: dict, evaluation: dict, where: str) -> dict:
    """``record`` with the methods of an ``examples/evaluate.py`` output added, after checking that
    they ran the record's test episodes with the record's policy and actor seed, and that a method
    the record holds too has the record's outcomes."""
    config, run = evaluation["config"], f"{record['task']} {record['policy']} seed {record['seed']}"
    if (config["seed"], config["episodes"]) != (record["eval_seed"], record["episodes"]):
        raise ValueError(
            f"{where} ran {config['episodes']} episodes of evaluation seed {config['seed']}, not the record's "
            f"{record['episodes']} of seed {record['eval_seed']}"
        )
    checkpoint = Path(config["policy_checkpoint"])
    if (
        checkpoint.parent.name != f"{record['policy']}_seed{record['seed']}"
        or checkpoint.parent.parent.name != record["task"]
    ):
        raise ValueError(f"{where} evaluated {checkpoint}, not the policy of {run}")
    if config["actor_seed"] != record["seed"]:
        raise ValueError(
            f"{where} ran at actor_seed={config['actor_seed']}; the main job's {run} ran at {record['seed']}"
        )
    added = {
        SHORT[name]: {"success_rate": row["success_rate"], "outcomes": outcome_string(row["records"])}
        for name, row in evaluation["success"].items()
    }
    for name, row in added.items():
        if name in record["methods"] and record["methods"][name].get("outcomes") != row["outcomes"]:
            raise ValueError(f"{where}: {name}'s outcomes are not those of the record of {run}")
    return {**record, "methods": {**record["methods"], **added}}


def compare(cfg: Config) -> dict:
    records = {}
    for record in load_records(cfg.records):
        key = (record["policy"], record["task"], str(record["seed"]))
        if record["variant"] == cfg.variant and records.setdefault(key, record) is not record:
            raise ValueError(f"two {cfg.variant} records of run {'/'.join(key)} under {cfg.records}")
    rows, pooled = [], [0, 0]
    for position, run in enumerate(cfg.runs):
        key = tuple(run.split("/"))
        if key not in records:
            raise ValueError(f"no {cfg.variant} record of run {run} under {cfg.records}")
        record = records[key]
        if cfg.evaluations:
            path = Path(cfg.evaluations[position])
            record = with_evaluation(record, json.loads(path.read_text()), str(path))
        missing = {cfg.method, cfg.against} - set(record["methods"])
        if missing:
            raise ValueError(f"the record of run {run} has no {sorted(missing)}")
        counts = discordant(record, cfg.method, cfg.against)
        if counts is None:
            raise ValueError(f"the record of run {run} keeps no per-episode outcomes of {cfg.method} and {cfg.against}")
        pooled = [pooled[0] + counts[0], pooled[1] + counts[1]]
        rows.append(
            {
                "run": run,
                "episodes": record["episodes"],
                "eval_seed": record["eval_seed"],
                cfg.against: record["methods"][cfg.against]["success_rate"],
                cfg.method: record["methods"][cfg.method]["success_rate"],
                "against_only": counts[0],
                "method_only": counts[1],
                "net": counts[1] - counts[0],
            }
        )
    test = sign_test(*pooled)
    return {
        "method": cfg.method,
        "against": cfg.against,
        "variant": cfg.variant,
        "runs": rows,
        "pooled": {"against_only": pooled[0], "method_only": pooled[1], "p_two_sided": test["p_value"]},
        "largest_net_loss": max(0, -min(row["net"] for row in rows)),
    }


def markdown(result: dict) -> str:
    method, against = result["method"], result["against"]
    lines = [
        f"| run | episodes | {against} (%) | {method} (%) | only {against} / only {method} |",
        "| --- | --- | --- | --- | --- |",
    ]
    for row in result["runs"]:
        lines.append(
            f"| {row['run']} | {row['episodes']} | {100 * row[against]:.0f} | {100 * row[method]:.0f} | "
            f"{row['against_only']} / {row['method_only']} |"
        )
    pooled = result["pooled"]
    lines.append(
        f"| pooled | | | | {pooled['against_only']} / {pooled['method_only']} "
        f"(two-sided p = {pooled['p_two_sided']:.3f}) |"
    )
    return "\n".join(lines) + f"\n\nLargest net loss of one run: {result['largest_net_loss']} episodes."


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    result = compare(cfg)
    print(markdown(result))
    if cfg.json:
        command = "python examples/paper/paired_comparison.py " + " ".join(argv)
        atomic_write(Path(cfg.json), json.dumps({"command": command, **result}, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
