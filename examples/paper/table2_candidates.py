"""Paper Table 2: where should DALI-R's candidate diversity come from?

    python examples/paper/table2_candidates.py policies=[.../disassemble/fm_seed0/checkpoint.pt] \\
        world_models=[.../world_model.pt]
    python examples/paper/table2_candidates.py policies=[a.pt,b.pt] world_models=[a_wm.pt,b_wm.pt] \\
        episodes=50 out=outputs/table2
    python examples/paper/table2_candidates.py ... sources=[dropout,cem] search.iterations=5 search.elites=8

Every (policy, world model) pair (one task and seed each) is evaluated on the same episodes with
the same frozen policy, world model, scorer and selection rule (the paper's arg-max), changing only
how the ``num_candidates`` candidate chunks are made: by perturbing the policy's input (``dropout``,
DALI-R's point dropout; ``noise``, Gaussian observation noise) or by searching the action space
around clean policy samples (``shooting``, ``cem``, ``mppi``, ``gradient``; settings under
``search.``, see :mod:`torchrl_dalir.reranking.search`); ``resample`` (clean policy samples alone)
is the action-space methods' starting point. The base policy runs once per pair, as the reference.
On MetaWorld the search leaves the gripper command as sampled (``keep_gripper``, as the paper does).

Writes ``<out>/table2.md`` (success per task, mean over seeds, and the average),
``<out>/table2.json`` (the same with every episode's outcome) and ``<out>/table2.png``.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.envs import get_task
from torchrl_dalir.evaluation.compare import (
    BASE,
    COMMON_NOISE,
    DALIR,
    evaluate_checkpoints,
    paired_sign_test,
    sign_test,
)
from torchrl_dalir.evaluation.plots import plot_success_by_task
from torchrl_dalir.pipeline.records import outcome_string
from torchrl_dalir.reranking import (
    CleanObservation,
    RerankingConfig,
    SearchConfig,
    SelectionConfig,
    candidate_generator,
)
from torchrl_dalir.utils import atomic_write, measured_once

INPUT_SOURCES = {"dropout": "point dropout", "noise": "observation noise", "resample": "policy samples"}
GENERATORS = {
    "dropout": "dropout",
    "noise": "noise",
    "resample": "clean",
}  # each input source's RerankingConfig.candidates
SEARCH_SOURCES = {"shooting": "random shooting", "cem": "CEM", "mppi": "MPPI", "gradient": "score-gradient ascent"}
SOURCES = {**INPUT_SOURCES, **SEARCH_SOURCES}
GRIPPER_DIMS = {
    "metaworld": [3],
    "adroit": [],
}  # MetaWorld actions are (dx, dy, dz, gripper); Adroit hands have no gripper


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
    sources: list[str] = field(default_factory=lambda: ["dropout", "noise", *SEARCH_SOURCES])  # among SOURCES
    episodes: int = 50
    seed: int = 0  # the evaluation seed: episodes never overlap data-generation episodes
    device: str = "cpu"
    num_candidates: int = RerankingConfig.num_candidates  # the candidate budget of every source
    dropout: float = RerankingConfig.dropout  # point-dropout probability
    noise_std: float = RerankingConfig.noise_std  # observation noise, metres
    search: SearchConfig = field(
        default_factory=SearchConfig
    )  # the action-space methods' settings (the method is the source)
    keep_gripper: bool = True  # the search leaves the gripper command as sampled (the paper)
    selection: SelectionConfig = field(
        default_factory=SelectionConfig
    )  # the same rule for every source (the paper: arg-max)
    actor_seed: int = 0
    common_noise: bool = COMMON_NOISE  # the clean candidate draws the base policy's own noise (common random numbers)
    out: str = "outputs/table2"


def candidate_source(name: str, cfg: Config, suite: str) -> dict:
    """The ``candidates`` and ``search`` of :func:`evaluate_checkpoints` for source ``name``."""
    if name in INPUT_SOURCES:
        return {
            "candidates": candidate_generator(
                RerankingConfig(candidates=GENERATORS[name], dropout=cfg.dropout, noise_std=cfg.noise_std)
            )
        }
    fixed = sorted({*cfg.search.fixed_dims, *(GRIPPER_DIMS[suite] if cfg.keep_gripper else [])})
    return {"candidates": CleanObservation(), "search": dataclasses.replace(cfg.search, method=name, fixed_dims=fixed)}


def evaluate_run(index: int, policy_path: str, world_model_path: str, cfg: Config) -> dict:
    """Every source of ``cfg`` and the base policy on one (policy, world model) pair, on the same episodes.
    Each method's row is kept in ``<out>/parts/`` as soon as it is measured, and a re-run with the same
    inputs reuses it: an interrupted table resumes at the method it was running."""
    task = load_policy(policy_path, cfg.device).task
    common = dict(
        episodes=cfg.episodes,
        seed=cfg.seed,
        device=cfg.device,
        num_candidates=cfg.num_candidates,
        actor_seed=cfg.actor_seed,
        selection=cfg.selection,
        common_noise=cfg.common_noise,
    )
    settings = {k: v for k, v in config_dict(cfg).items() if k not in ("policies", "world_models", "sources", "out")}

    def measured(name: str, measure) -> dict:
        inputs = {"policy": policy_path, "world_model": world_model_path, "method": name, **settings}
        return measured_once(Path(cfg.out) / "parts" / f"{index}_{task}" / f"{name}.json", inputs, measure)

    methods = {
        "base": measured(
            "base", lambda: evaluate_checkpoints(policy_path, world_model_path, methods=["base"], **common)[BASE]
        )
    }
    for name in cfg.sources:
        source = candidate_source(name, cfg, get_task(task).suite)
        row = measured(
            name,
            lambda: evaluate_checkpoints(policy_path, world_model_path, methods=["dalir"], **common, **source)[DALIR],
        )
        methods[name] = {**row, **({"search": source["search"].name} if "search" in source else {})}
    return {"task": task, "policy": policy_path, "world_model": world_model_path, "methods": methods}


def success_table(runs: list[dict], keys: list[str]) -> list[dict]:
    """One row per task: every method's per-seed success rates (the input of :func:`plot_success_by_task`)
    and, per source, the test episodes that only the base policy / only the source solved, summed
    over seeds, with the sign test (``vs_base``)."""
    tasks = list(dict.fromkeys(run["task"] for run in runs))
    rows = []
    for task in tasks:
        own = [r for r in runs if r["task"] == task]
        row = {"task": task, **{k: [r["methods"][k]["success_rate"] for r in own] for k in keys}, "vs_base": {}}
        for k in keys[1:]:
            pairs = [
                paired_sign_test(*[[e["success"] for e in r["methods"][m]["records"]] for m in ("base", k)])
                for r in own
            ]
            row["vs_base"][k] = sign_test(sum(p["base_only"] for p in pairs), sum(p["dalir_only"] for p in pairs))
        rows.append(row)
    return rows


def compact(run: dict) -> dict:
    """A run with each method's episode records as one string of outcomes (``"0110..."``, in
    episode order): the table's JSON stays small, and the pairing can be redone from it."""
    methods = {
        name: {**{k: v for k, v in row.items() if k != "records"}, "outcomes": outcome_string(row["records"])}
        for name, row in run["methods"].items()
    }
    return {**run, "methods": methods}


def markdown(table: list[dict], keys: list[str], labels: dict[str, str]) -> str:
    """Success (%) per task, mean over seeds, and the average over tasks."""

    def mean(values):
        return 100 * sum(values) / len(values)

    lines = [
        "| method | variation | " + " | ".join(row["task"] for row in table) + " | avg. |",
        "| --- | --- |" + " --- |" * (len(table) + 1),
    ]
    for k in keys:
        target = "none" if k == "base" else ("action chunk" if k in SEARCH_SOURCES else "policy input")
        cells = [mean(row[k]) for row in table]
        paired = [
            "" if k == "base" else " ({base_only} / {dalir_only}, p = {p_value:.3f})".format(**row["vs_base"][k])
            for row in table
        ]
        lines.append(
            f"| {labels[k]} | {target} | "
            + " | ".join(f"{c:.1f}{d}" for c, d in zip(cells, paired))
            + f" | {sum(cells) / len(cells):.1f} |"
        )
    seeds = sorted({len(row["base"]) for row in table})
    return "\n".join(lines) + (
        f"\n\nSeeds per task: {', '.join(map(str, seeds))}. In brackets: the test episodes only the base "
        "policy / only the source solved, summed over seeds, and the two-sided sign test.\n"
    )


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    unknown = set(cfg.sources) - set(SOURCES)
    if unknown:
        raise ValueError(f"unknown sources {sorted(unknown)}; choose among {sorted(SOURCES)}")
    if len(cfg.policies) != len(cfg.world_models):
        raise ValueError(
            f"{len(cfg.policies)} policies but {len(cfg.world_models)} world models: give one world model per policy"
        )
    runs = [evaluate_run(i, p, w, cfg) for i, (p, w) in enumerate(zip(cfg.policies, cfg.world_models))]
    keys = ["base", *cfg.sources]
    labels = {"base": "base policy", **SOURCES}
    table = success_table(runs, keys)
    text = markdown(table, keys, labels)
    print(text)
    out = Path(cfg.out)
    atomic_write(out / "table2.md", text)
    atomic_write(
        out / "table2.json",
        json.dumps({"config": config_dict(cfg), "table": table, "runs": [compact(run) for run in runs]}, indent=1),
    )
    plot_success_by_task(
        table,
        out / "table2.png",
        title="Where candidate diversity comes from",
        methods=tuple((k, labels[k]) for k in keys),
    )


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
