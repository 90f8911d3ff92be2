"""Success rate of a trained base policy, and of DALI-R on top of it, on the same episodes.

    python examples/evaluate.py policy_checkpoint=outputs/pipeline/policies/disassemble/fm_seed0/checkpoint.pt
    python examples/evaluate.py policy_checkpoint=.../checkpoint.pt world_model=.../world_model.pt episodes=100
    python examples/evaluate.py policy_checkpoint=... world_model=... methods=[random]   # the random-choice control
    python examples/evaluate.py policy_checkpoint=... methods=[base,dropout]   # the base policy on point-dropout views
    # another rule:
    python examples/evaluate.py policy_checkpoint=... world_model=... methods=[dalir] selection.rule=argmax
    # a chunk critic trained on branched outcomes, no world model, reranking each episode's first decision only:
    python examples/evaluate.py policy_checkpoint=... critic=.../critic.pt num_candidates=8 decisions=1
    # GIFs of the first 2 episodes of each method:
    python examples/evaluate.py policy_checkpoint=... world_model=... video=2

Prints a table and writes ``<out>/evaluation.json`` (rates and per-episode records) and
``<out>/evaluation.csv`` (one row per method and episode; DALI-R's rows also describe its choices,
see ``evaluation.compare.decision_summary``); with ``video=n``, ``<out>/videos/<method>_episode_<i>.gif``
of the first ``n`` episodes of each method (the same episodes for each).
"""

from __future__ import annotations

import csv
import io
import json
import sys
from dataclasses import dataclass

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.evaluation.compare import COMMON_NOISE, check_evaluation_settings, evaluate_checkpoints
from torchrl_dalir.reranking import RerankingConfig, SelectionConfig
from torchrl_dalir.utils import atomic_write, writable_dir


@dataclass
class Config:
    policy_checkpoint: str = "outputs/pipeline/policies/disassemble/fm_seed0/checkpoint.pt"
    world_model: str | None = None  # add DALI-R with this world model (trained on top of ``policy_checkpoint``)
    critic: str | None = None  # a chunk critic (critic.pt) to select with: alone, or with selection.scorer=critic
    episodes: int = 50
    seed: int = 0  # the evaluation seed: episodes never overlap data-generation episodes
    device: str = "cpu"
    num_candidates: int = RerankingConfig.num_candidates
    dropout: float = RerankingConfig.dropout
    decisions: int = RerankingConfig.decisions  # rerank only each episode's first <decisions> decisions (0: all)
    actor_seed: int = 0
    # among base, dalir, argmax, random (DALI-R's candidates chosen at random), dropout (one point-dropout candidate)
    methods: list[str] | None = None
    selection: SelectionConfig | None = None  # DALI-R's rule (selection.rule=argmax ...); default: the checkpoint's
    common_noise: bool = (
        COMMON_NOISE  # DALI-R's clean candidate draws the base policy's own noise (common random numbers)
    )
    out: str = "outputs/evaluation"
    video: int = 0  # record the first <video> episodes of each method as GIFs under <out>/videos/

    def __post_init__(self):
        check_evaluation_settings(self.episodes, self.seed, self.num_candidates, self.dropout, video=self.video)


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    out = writable_dir(cfg.out)  # now, not after the episodes
    rows = evaluate_checkpoints(
        cfg.policy_checkpoint,
        cfg.world_model,
        episodes=cfg.episodes,
        seed=cfg.seed,
        device=cfg.device,
        reranking=RerankingConfig(
            num_candidates=cfg.num_candidates,
            dropout=cfg.dropout,
            selection=cfg.selection,
            common_noise=cfg.common_noise,
            decisions=cfg.decisions,
        ),
        critic=cfg.critic,
        actor_seed=cfg.actor_seed,
        methods=cfg.methods,
        video=cfg.video,
        video_dir=out / "videos",
    )
    print(f"\n{'method':16s} {'success':>8s} {'episodes':>9s} {'seconds':>8s}")
    for name, row in rows.items():
        print(f"{name:16s} {row['success_rate']:8.1%} {row['episodes']:9d} {row['seconds']:8.1f}")
    atomic_write(out / "evaluation.json", json.dumps({"config": config_dict(cfg), "success": rows}, indent=1))
    table = io.StringIO()
    details = sorted({key for row in rows.values() for record in row["records"] for key in record["details"]})
    writer = csv.DictWriter(table, ["method", "episode", "reset_seed", "success", "steps", "episode_return", *details])
    writer.writeheader()
    for name, row in rows.items():
        writer.writerows(
            {"method": name, **{k: v for k, v in record.items() if k != "details"}, **record["details"]}
            for record in row["records"]
        )
    atomic_write(out / "evaluation.csv", table.getvalue())


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
