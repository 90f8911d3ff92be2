"""Train a base 3D policy (flow matching or DP3 diffusion) on one task's expert demos.

    python examples/train_policy.py task=disassemble policy=fm preset=cpu seed=0
    python examples/train_policy.py task=disassemble policy=dp preset=paper device=cuda
    torchrun --nproc_per_node=4 examples/train_policy.py task=disassemble policy=dp preset=paper device=cuda

Under torchrun the training is data-parallel (``batch_size`` stays the global batch) and rank 0
alone writes, evaluates and prints. Reads ``<data>/<task>/demos`` (make it with ``examples/collect_data.py``), writes
``<out>/<task>/<policy>_seed<seed>/checkpoint.pt`` (resumed if it exists) and logs; with
``eval_episodes=N`` it then evaluates the EMA policy on N evaluation episodes.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.config import check_at_least, parse_config
from torchrl_dalir.evaluation import evaluate
from torchrl_dalir.modules.receding_horizon import receding_horizon
from torchrl_dalir.seeds import check_eval_seed
from torchrl_dalir.training import POLICY_PRESETS, PolicyTrainingConfig, distributed, train_policy
from torchrl_dalir.utils import atomic_write


@dataclass
class Config(PolicyTrainingConfig):
    eval_episodes: int = 0  # 0: no evaluation
    eval_seed: int = 0

    def __post_init__(self):
        super().__post_init__()
        check_at_least("eval_episodes", self.eval_episodes, 0)
        check_eval_seed(self.eval_seed, "eval_seed")


def main(argv: list[str]) -> None:
    cfg = parse_config(Config, argv, POLICY_PRESETS)
    start = time.perf_counter()
    path = train_policy(cfg)
    if not distributed.is_main():
        return
    print(f"trained {cfg.policy} on {cfg.task} in {time.perf_counter() - start:.0f} s: {path}")
    if cfg.eval_episodes:
        policy = load_policy(path, cfg.device, task=cfg.task)
        actor = receding_horizon(policy)
        result = evaluate(
            actor,
            cfg.task,
            cfg.eval_episodes,
            cfg.eval_seed,
            num_points=policy.num_points,
            history=cfg.model.obs_steps,
            device=cfg.device,
            progress=cfg.progress,
        )
        atomic_write(path.parent / f"eval_seed{cfg.eval_seed}.json", json.dumps(result.to_dict(), indent=1))
        print(
            f"{cfg.task} {cfg.policy} seed {cfg.seed}: "
            f"success {result.success_rate:.1%} over {cfg.eval_episodes} episodes"
        )


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
