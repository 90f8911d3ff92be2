"""Paper Figure 3(b): DALI-R's success as the number of candidates grows.

    python examples/paper/candidate_scaling.py policies=[<run>/policies/disassemble/dp_seed0/checkpoint.pt] \\
        world_models=[<run>/world_models/dp/disassemble/seed0_frozen+explore_dp_seed0/world_model.pt]
    python examples/paper/candidate_scaling.py policies=[a.pt,b.pt] world_models=[a_wm.pt,b_wm.pt] \\
        candidates=[2,4,8,16,32,64] methods=[argmax,random]

Every (policy, world model) pair (one task and seed each) runs the base policy once and, for each
candidate count N in ``candidates``, each reranking method (``argmax``: the paper's arg-max of the
state scorer; ``random``: a random pick among the same candidates; ``dalir``: the checkpoint's
calibrated rule) over N point-dropout candidates, one of them clean, on the same test episodes.
With common noise the clean candidate alone is the base policy, so the base policy is N = 1.
Each row is paired with the base policy on the same episodes (the sign test), and kept in
``<out>/parts/`` as soon as it is measured: an interrupted run resumes at the row it was measuring.

Writes ``<out>/candidate_scaling.md`` (success per N), ``.json`` (with every episode's outcome) and
``.png`` (success against N, one line per pair and method, the base policy at N = 1).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.checkpoints import load_policy, load_world_model
from torchrl_dalir.config import check_at_least, check_choice, config_dict, parse_config
from torchrl_dalir.evaluation.compare import (
    COMMON_NOISE,
    METHODS,
    RERANKING,
    check_evaluation_settings,
    evaluate_checkpoints,
    paired_sign_test,
    replays_base_policy,
)
from torchrl_dalir.evaluation.plots import plot_candidate_scaling
from torchrl_dalir.pipeline.records import outcome_string, successes
from torchrl_dalir.reranking import RerankingConfig, SelectionConfig
from torchrl_dalir.utils import atomic_write, measured_once, writable_dir

BASE_INPUTS = ("episodes", "seed", "device", "actor_seed")  # what the base policy's row depends on, besides the policy


@dataclass
class Config:
    policies: list[str] = field(
        default_factory=lambda: ["outputs/pipeline/policies/disassemble/fm_seed0/checkpoint.pt"]
    )
    world_models: list[str] = field(
        default_factory=lambda: [
            "outputs/pipeline/world_models/fm/disassemble/seed0_frozen+explore_fm_seed0/world_model.pt"
        ]
    )
    candidates: list[int] = field(
        default_factory=lambda: [4, 8, 16, 32]
    )  # N (the paper's); N = 1 is the base policy itself
    methods: list[str] = field(default_factory=lambda: ["argmax"])  # among RERANKING
    episodes: int = 50
    seed: int = 0  # the evaluation seed: episodes never overlap data-generation episodes
    device: str = "cpu"
    dropout: float = RerankingConfig.dropout  # point-dropout probability of every candidate but the clean one
    actor_seed: int = 0
    common_noise: bool = (
        COMMON_NOISE  # the clean candidate draws the base policy's own noise: N = 1 replays the base policy
    )
    out: str = "outputs/candidate_scaling"

    def __post_init__(self):
        if not self.methods or not self.candidates:
            raise ValueError(
                f"methods and candidates need at least one entry each, got {self.methods} and {self.candidates}"
            )
        for method in self.methods:
            check_choice("methods", method, RERANKING)
        for n in self.candidates:
            check_at_least("candidates (N = 1 is the base policy, always run)", n, 2)
        check_evaluation_settings(self.episodes, self.seed, max(self.candidates), self.dropout)
        if len(self.policies) != len(self.world_models):
            raise ValueError(
                f"{len(self.policies)} policies but {len(self.world_models)} world models: "
                "give one world model per policy"
            )
        self.candidates = sorted(set(self.candidates))


def evaluate_run(index: int, policy_path: str, world_model_path: str, cfg: Config) -> dict:
    """The base policy, then every method at every candidate count, on one (policy, world model) pair;
    each row's episode outcomes as one string (``"0110..."``). A method whose rule keeps the clean
    candidate (``dalir`` after a calibration that kept the base policy) replays the base policy's row,
    and two methods with the same rule share one row."""
    policy = load_policy(policy_path, cfg.device)
    rules = {
        "argmax": SelectionConfig(),
        "dalir": load_world_model(world_model_path, policy=policy).selection,
        "random": None,
    }
    settings = {
        k: v
        for k, v in config_dict(cfg).items()
        if k not in ("policies", "world_models", "candidates", "methods", "out")
    }
    folder = Path(cfg.out) / "parts" / f"{index}_{policy.task}"

    def measure(method: str, num_candidates: int):
        def run():
            row = evaluate_checkpoints(
                policy_path, world_model_path, methods=[method], num_candidates=num_candidates, **settings
            )[METHODS[method]]
            return {
                "success_rate": row["success_rate"],
                "outcomes": outcome_string(row["records"]),
                "seconds": row["seconds"],
                **({"selection": row["selection"]} if "selection" in row else {}),
            }

        return run

    base = measured_once(
        folder / "base.json", {"policy": policy_path, **{k: settings[k] for k in BASE_INPUTS}}, measure("base", 1)
    )
    rows, by_rule = {}, {}
    for method in cfg.methods:
        rule = rules[method]
        if rule is not None and replays_base_policy(rule, cfg.common_noise):
            rows[method] = {
                str(n): {**base, "selection": rule.name, "seconds": 0.0, "replays": "base policy"}
                for n in cfg.candidates
            }
            continue
        if rule is not None and rule.name in by_rule:
            rows[method] = by_rule[rule.name]
            continue
        inputs = {
            "policy": policy_path,
            "world_model": world_model_path,
            **settings,
            "method": method,
            "rule": rule and rule.name,
        }
        rows[method] = {
            str(n): measured_once(folder / f"{method}_{n}.json", {**inputs, "num_candidates": n}, measure(method, n))
            for n in cfg.candidates
        }
        if rule is not None:
            by_rule[rule.name] = rows[method]
    return {
        "task": policy.task,
        "label": f"{policy.task} {Path(policy_path).parent.name}",
        "policy": policy_path,
        "world_model": world_model_path,
        "base": base,
        "methods": rows,
    }


def scaling_table(runs: list[dict]) -> list[dict]:
    """One row per (pair, method): success per candidate count, N = 1 being the base policy, and per
    count the test episodes only the base policy / only the method solved, with the sign test."""
    table = []
    for run in runs:
        base = successes(run["base"]["outcomes"])
        for method, by_n in run["methods"].items():
            paired = {n: paired_sign_test(base, successes(row["outcomes"])) for n, row in by_n.items()}
            table.append(
                {
                    "run": run["label"],
                    "method": method,
                    "candidates": [1, *map(int, by_n)],
                    "success": [run["base"]["success_rate"], *(row["success_rate"] for row in by_n.values())],
                    "vs_base": {
                        n: {"base_only": t["base_only"], "method_only": t["dalir_only"], "p_value": t["p_value"]}
                        for n, t in paired.items()
                    },
                }
            )
    return table


def markdown(table: list[dict], episodes: int) -> str:
    """Success (%) per run, method and candidate count, with the pairing against the base policy."""
    counts = table[0]["candidates"]  # every row has the configuration's counts
    lines = [
        "| run | method | " + " | ".join("N = 1 (base)" if n == 1 else f"N = {n}" for n in counts) + " |",
        "| --- | --- |" + " --- |" * len(counts),
    ]
    for row in table:
        cells = [f"{100 * row['success'][0]:.1f}"]
        for n, rate in zip(counts[1:], row["success"][1:]):
            test = row["vs_base"][str(n)]
            cells.append(f"{100 * rate:.1f} ({test['base_only']} / {test['method_only']}, p = {test['p_value']:.2f})")
        lines.append(f"| {row['run']} | {row['method']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + (
        f"\n\nSuccess (%) on {episodes} test episodes per run; in brackets the episodes only the base "
        "policy / only the method solved, and the two-sided sign test.\n"
    )


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    out = writable_dir(cfg.out)  # now, not after the episodes
    runs = [evaluate_run(i, p, w, cfg) for i, (p, w) in enumerate(zip(cfg.policies, cfg.world_models))]
    table = scaling_table(runs)
    text = markdown(table, cfg.episodes)
    print(text)
    atomic_write(out / "candidate_scaling.md", text)
    atomic_write(
        out / "candidate_scaling.json", json.dumps({"config": config_dict(cfg), "table": table, "runs": runs}, indent=1)
    )
    plot_candidate_scaling(table, out / "candidate_scaling.png")


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
