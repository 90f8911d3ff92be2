"""Milliseconds per decision of the base policies alone and with DALI-R (the paper's Table 5).

    python examples/benchmarks/benchmark_latency.py preset=cpu candidates=[1,4,8,16,32]
    python examples/benchmarks/benchmark_latency.py kinds=[fm] candidates=[32] \\
        precisions=[fp32,bf16]  # bf16 autocast at inference

Builds FM and DP policies and a latent world model and scorer with the ``preset``'s
architectures (untrained: latency does not depend on the weights), then times full decisions
on one observation of ``num_points`` points: median of ``repeats`` decisions after ``warmup``,
all in one process. The table gives each time and its ratio to the base policy alone (the
issue's goals: FM + DALI-R at 32 candidates at most 3x FM, DP + DALI-R at most 2x DP).
``precisions=[fp32,bf16]`` times every decision under each precision (bf16: autocast, as
training's ``precision=bf16``), one row per backbone and precision.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field

import torch
from tensordict import TensorDict

from torchrl_dalir import RerankingActor, keys
from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.evaluation.timing import median_ms
from torchrl_dalir.modules import LatentEncoder, LatentWorldModel, PolicyConfig, TaskCompletionScorer, make_policy
from torchrl_dalir.training import POLICY_PRESETS, WORLD_MODEL_PRESETS, WorldModelTrainingConfig
from torchrl_dalir.training.precision import autocast_dtype
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    preset: str = "cpu"
    kinds: list[str] = field(default_factory=lambda: ["fm", "dp"])
    euler_steps: int = 1  # of the FM policy (DP keeps the preset's DDIM steps)
    candidates: list[int] = field(default_factory=lambda: [1, 4, 8, 16, 32])
    precisions: list[str] = field(default_factory=lambda: ["fp32"])  # fp32 | bf16 (autocast) | auto
    num_points: int = 512
    action_dim: int = 4
    state_dim: int = 4
    warmup: int = 5
    repeats: int = 30
    threads: int = 2
    out: str = "outputs/benchmarks/latency.json"


@torch.no_grad()
def main(argv: list[str]) -> None:
    cfg = parse_config(Config, argv)
    torch.set_num_threads(cfg.threads)
    wm = parse_config(WorldModelTrainingConfig, [f"preset={cfg.preset}"], WORLD_MODEL_PRESETS)  # checks the preset name
    model_preset = POLICY_PRESETS[cfg.preset].get("model", {})
    obs = TensorDict(
        {keys.POINT_CLOUD: torch.rand(1, 2, cfg.num_points, 3), keys.AGENT_POS: torch.rand(1, 2, cfg.state_dim)}, [1]
    )
    rows = []
    for kind in cfg.kinds:
        policy_cfg = PolicyConfig(kind=kind, **model_preset)
        policy_cfg.euler_steps = cfg.euler_steps
        policy = make_policy(policy_cfg, cfg.action_dim, cfg.state_dim).eval()
        encoder = LatentEncoder.from_policy(policy)
        world_model = LatentWorldModel(
            encoder.latent_dim, cfg.action_dim, policy_cfg.action_steps, wm.wm_hidden, wm.wm_layers, wm.wm_heads
        )
        scorer = TaskCompletionScorer(encoder.latent_dim, wm.scorer_hidden)
        for precision in cfg.precisions:
            dtype = autocast_dtype(precision, "cpu")
            with torch.autocast("cpu", dtype=dtype or torch.bfloat16, enabled=dtype is not None):
                base_ms = median_ms(lambda: policy(obs.clone()), cfg.warmup, cfg.repeats)
                row = {
                    "kind": kind,
                    "precision": precision,
                    "steps": policy_cfg.euler_steps if kind == "fm" else policy_cfg.ddim_steps,
                    "base_policy_ms": round(base_ms, 2),
                }
                for n in cfg.candidates:
                    actor = RerankingActor(policy, encoder, world_model, scorer, num_candidates=n)
                    row[f"dalir_{n}_ms"] = round(median_ms(lambda: actor(obs.clone()), cfg.warmup, cfg.repeats), 2)
            rows.append(row)
            print(json.dumps(row), flush=True)
    header = (
        "| N_cand | " + " | ".join(f"{r['kind'].upper()} ({r['precision']}) + DALI-R ms (x base)" for r in rows) + " |"
    )
    lines = [
        header,
        "|" + " --- |" * (len(rows) + 1),
        "| base policy | " + " | ".join(f"{r['base_policy_ms']:.1f} (1.00)" for r in rows) + " |",
    ]
    for n in cfg.candidates:
        lines.append(
            f"| {n} | "
            + " | ".join(f"{r[f'dalir_{n}_ms']:.1f} ({r[f'dalir_{n}_ms'] / r['base_policy_ms']:.2f})" for r in rows)
            + " |"
        )
    print("\n".join(lines))
    atomic_write(cfg.out, json.dumps({"config": config_dict(cfg), "rows": rows, "table": lines}, indent=1))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
