"""Success rates and speed of the experts and their drift-noise versions (state-only envs, no
rendering; the speed is wall-clock env steps per second, the env included).

    python examples/maintainer/evaluate_experts.py tasks=[disassemble,shelf-place] noise_scales=[0,0.1] episodes=50

Writes ``<out>/experts.json`` and prints a table; the noise levels shipped in the collection
presets were chosen from this table so that the mixed data holds successes and failures.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.envs.tasks import get_task
from torchrl_dalir.evaluation import evaluate
from torchrl_dalir.experts import add_drift_noise, make_expert
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    tasks: list[str] = field(default_factory=lambda: ["disassemble", "shelf-place", "stick-pull", "pick-place-wall"])
    noise_scales: list[float] = field(default_factory=lambda: [0.0, 0.05, 0.1, 0.15, 0.2, 0.3])
    noise_correlation: float = 0.9
    episodes: int = 50
    seed: int = 0
    out: str = "outputs/experts"


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    for task in cfg.tasks:
        get_task(task)  # an unknown name fails before the first task runs
    rows = []
    for task in cfg.tasks:
        for scale in cfg.noise_scales:
            policy = make_expert(task)
            if scale > 0:
                policy = add_drift_noise(policy, scale, cfg.noise_correlation, seed=cfg.seed)
            start = time.perf_counter()
            result = evaluate(policy, task, cfg.episodes, cfg.seed, render=False, progress=False)
            steps_per_s = sum(e.steps for e in result.episodes) / (time.perf_counter() - start)
            rows.append(
                {
                    "task": task,
                    "noise_scale": scale,
                    "success_rate": result.success_rate,
                    "episodes": cfg.episodes,
                    "steps_per_s": round(steps_per_s, 1),
                }
            )
            print(
                f"{task:18s} noise {scale:5.2f}  success {result.success_rate:6.1%}  ({cfg.episodes} episodes, "
                f"{steps_per_s:.0f} env steps/s with the env)",
                flush=True,
            )
    out = Path(cfg.out)
    atomic_write(out / "experts.json", json.dumps({"config": config_dict(cfg), "rows": rows}, indent=2))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
