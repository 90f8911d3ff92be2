"""Does DALI-R's imagination order its candidates the way the simulator does?

    python examples/paper/diagnose_reranking.py policy_checkpoint=.../checkpoint.pt world_model=.../world_model.pt
    python examples/paper/diagnose_reranking.py policy_checkpoint=... world_model=... \\
        follow_through=true decisions=25 stride=5

At the first ``decisions`` decisions of ``episodes`` evaluation episodes (along the base policy),
runs every candidate's executed actions in the simulator from the same state and compares the
scorer's rating of the imagined and of the real outcome
(:func:`torchrl_dalir.branching.candidate_outcomes.candidate_outcomes`). ``follow_through=true``
also continues each candidate with the base policy to the episode's end, to see whether the
scorer prefers the candidates that go on to succeed (slow: one rest-of-episode rollout per
candidate; use ``stride`` to spread fewer decisions over whole episodes). Prints a summary and
writes ``<out>/candidate_outcomes.json`` and ``<out>/candidate_outcomes.png``.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass

import torch

from torchrl_dalir import RerankingActor
from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.branching.candidate_outcomes import candidate_outcomes, summarize_candidate_outcomes
from torchrl_dalir.config import check_at_least, config_dict, parse_config
from torchrl_dalir.evaluation.calibration import VALIDATION_SEED
from torchrl_dalir.evaluation.compare import check_evaluation_settings
from torchrl_dalir.evaluation.plots import plot_candidate_outcomes
from torchrl_dalir.reranking import RerankingConfig, SelectionConfig
from torchrl_dalir.utils import atomic_write, writable_dir


@dataclass
class Config:
    policy_checkpoint: str = "outputs/pipeline/policies/disassemble/fm_seed0/checkpoint.pt"
    world_model: str = "outputs/pipeline/world_models/fm/disassemble/seed0_frozen+explore_fm_seed0/world_model.pt"
    episodes: int = 5
    decisions: int = 10  # the first decisions of each episode
    stride: int = 1  # analyse every stride-th of them (the others just follow the base policy)
    follow_through: bool = False  # continue every candidate with the base policy to the episode's end
    seed: int = VALIDATION_SEED  # the evaluation seed (episodes as in examples/evaluate.py); not the test episodes' 0
    num_candidates: int = RerankingConfig.num_candidates
    dropout: float = RerankingConfig.dropout
    actor_seed: int = 0
    device: str = "cpu"
    out: str = "outputs/candidate_outcomes"

    def __post_init__(self):
        check_evaluation_settings(self.episodes, self.seed, self.num_candidates, self.dropout)
        check_at_least("decisions", self.decisions, 1)
        check_at_least("stride", self.stride, 1)


def main(argv: list[str]) -> dict:
    cfg: Config = parse_config(Config, argv)
    out = writable_dir(cfg.out)  # now, not after the episodes
    torch.manual_seed(cfg.actor_seed)
    # imagined and real outcomes rated by the same (state) scorer; "chosen" is its arg-max
    reranking = RerankingConfig(num_candidates=cfg.num_candidates, dropout=cfg.dropout, selection=SelectionConfig())
    actor = RerankingActor.from_checkpoints(
        cfg.policy_checkpoint, cfg.world_model, cfg.device, config=reranking, seed=cfg.actor_seed
    )
    task = actor.policy.task
    records = candidate_outcomes(
        actor,
        task,
        episodes=cfg.episodes,
        decisions=cfg.decisions,
        stride=cfg.stride,
        follow_through=cfg.follow_through,
        seed=cfg.seed,
    )
    summary = summarize_candidate_outcomes(records)
    for key, value in summary.items():
        shown = (
            f"{value:.4g}"
            if isinstance(value, float)
            else [round(v, 3) for v in value]
            if isinstance(value, list)
            else value
        )
        print(f"{key:40s} {shown}")
    atomic_write(
        out / "candidate_outcomes.json",
        json.dumps({"config": config_dict(cfg), "summary": summary, "records": records}, indent=1),
    )
    plot_candidate_outcomes(
        records, out / "candidate_outcomes.png", title=f"{task}: DALI-R's candidates, imagined vs real"
    )
    return summary


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
