"""Evaluation time with point clouds rendered at every step against only where decisions read them.

    python examples/benchmarks/benchmark_evaluation.py policy_checkpoint=<policy.pt> \\
        world_model=<world_model.pt> episodes=5

Runs the base policy (and DALI-R, given a world model) on the same ``episodes`` validation
episodes twice: with the env rendering a cloud at every step (``decision_period=1``) and with the
evaluation's default, a cloud only for the observations that the receding-horizon decisions read.
Checks that both give the same episodes, and prints the wall and CPU milliseconds per env step
and their ratio.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from torchrl_dalir import RerankingActor
from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.config import check_at_least, parse_config
from torchrl_dalir.evaluation import evaluate
from torchrl_dalir.modules.receding_horizon import receding_horizon
from torchrl_dalir.reranking import RerankingConfig
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    policy_checkpoint: str = ""
    world_model: str = ""  # "" times the base policy only
    episodes: int = 5
    seed: int = 1  # validation episodes: timing reads no test episode
    num_candidates: int = RerankingConfig.num_candidates
    threads: int = 1
    out: str = "outputs/benchmarks"

    def __post_init__(self):
        if not self.policy_checkpoint:
            raise ValueError("policy_checkpoint=<path to a policy checkpoint> is required")
        check_at_least("episodes", self.episodes, 1)
        check_at_least("threads", self.threads, 1)


def timed(actor, task: str, cfg: Config, **env_kwargs) -> tuple[list[dict], dict]:
    """The episodes' records and the seconds (wall, CPU) per env step of one evaluation."""
    actor.reset(0)
    wall, cpu = time.perf_counter(), time.process_time()
    result = evaluate(actor, task, cfg.episodes, cfg.seed, progress=False, **env_kwargs)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    steps = sum(e.steps for e in result.episodes)
    return result.to_dict()["episodes"], {
        "env_steps": steps,
        "wall_ms_per_step": 1000 * wall / steps,
        "cpu_ms_per_step": 1000 * cpu / steps,
    }


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    torch.set_num_threads(cfg.threads)
    policy = load_policy(cfg.policy_checkpoint)
    actors = {"base policy": receding_horizon(policy)}
    if cfg.world_model:
        actors["DALI-R"] = receding_horizon(
            RerankingActor.on_policy(policy, cfg.world_model, num_candidates=cfg.num_candidates, seed=0)
        )
    env_kwargs = {"num_points": policy.num_points, "history": policy.config.obs_steps}
    rows = []
    for name, actor in actors.items():
        evaluate(
            actor, policy.task, 1, cfg.seed, progress=False, max_steps=2 * policy.config.action_steps, **env_kwargs
        )  # warm-up
        every_records, every = timed(actor, policy.task, cfg, decision_period=1, **env_kwargs)
        lazy_records, lazy = timed(actor, policy.task, cfg, **env_kwargs)
        if lazy_records != every_records:
            raise RuntimeError(f"{name}: the episodes differ between the two ways of rendering")
        row = {
            "method": name,
            "every_step": every,
            "decisions_only": lazy,
            "cpu_speedup": every["cpu_ms_per_step"] / lazy["cpu_ms_per_step"],
            "wall_speedup": every["wall_ms_per_step"] / lazy["wall_ms_per_step"],
        }
        rows.append(row)
        print(
            f"{policy.task}, {name}, {every['env_steps']} env steps (the same episodes both ways): "
            f"clouds at every step {every['wall_ms_per_step']:.1f} ms/step wall ({every['cpu_ms_per_step']:.1f} CPU), "
            "only where decisions read them "
            f"{lazy['wall_ms_per_step']:.1f} ms ({lazy['cpu_ms_per_step']:.1f} CPU): {row['wall_speedup']:.2f}x wall, "
            f"{row['cpu_speedup']:.2f}x CPU",
            flush=True,
        )
    atomic_write(
        Path(cfg.out) / f"evaluation_{policy.task}.json", json.dumps({"config": vars(cfg), "rows": rows}, indent=1)
    )


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
