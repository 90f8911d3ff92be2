"""Inference latency and candidate diversity of trained base policies.

    python examples/benchmarks/benchmark_policy.py \\
        checkpoints=[outputs/policies/disassemble/fm_seed0/checkpoint.pt] nfe=[1,10]

Latency: milliseconds per decision (median of ``repeats`` after ``warmup``), batch 1 and a batch
of ``candidates`` chunks from one observation, split into the encoder (per-point MLP, pooling,
state MLP) and the generator (DDIM or Euler steps). Diversity: mean pairwise L2 distance between
``candidates`` chunks from one demo observation, when only the noise is re-sampled, under point
dropout with fresh noise, and under point dropout with the same noise; averaged over
``observations`` observations spread evenly over the demos. With ``plot=true`` (the default) the
middle observation's chunks are drawn on their two principal components,
``<out folder>/candidates_<task>_<checkpoint folder>_steps<steps>.png`` (the paper's Figure 3(c)).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchrl_dalir import keys
from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.config import parse_config
from torchrl_dalir.data import TrajectoryDataset
from torchrl_dalir.data.windows import TrajectoryWindows
from torchrl_dalir.evaluation.plots import plot_candidate_spread
from torchrl_dalir.evaluation.timing import median_ms
from torchrl_dalir.reranking import RerankingConfig
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    checkpoints: list[str] = field(default_factory=list)
    data: str = "outputs/data"  # a demo observation comes from <data>/<task>/demos
    nfe: list[int] = field(default_factory=lambda: [1, 10])  # FM Euler steps to time (DP keeps its DDIM steps)
    candidates: int = RerankingConfig.num_candidates
    observations: int = 8  # demo observations the diversity is averaged over
    dropout: float = RerankingConfig.dropout
    warmup: int = 5
    repeats: int = 30
    threads: int = 2
    seed: int = 0
    plot: bool = True  # draw the middle observation's chunks (paper Figure 3(c)) next to out
    out: str = "outputs/benchmarks/policy.json"


def mean_pairwise_distance(chunks: torch.Tensor) -> float:
    flat = chunks.reshape(chunks.shape[0], -1)
    d = torch.cdist(flat, flat)
    n = flat.shape[0]
    return (d.sum() / (n * (n - 1))).item()


def candidate_chunks(policy, cloud, agent_pos, n: int, dropout: float, g: torch.Generator) -> dict[str, torch.Tensor]:
    """``n`` chunks ``[n, H, A]`` from one observation under three sources of variety: the sampling
    noise alone, point dropout with fresh noise (DALI-R's candidates) and point dropout alone."""
    cond = policy.encode(cloud, agent_pos)
    keep = torch.rand(n, *cloud.shape[1:3], generator=g) >= dropout
    keep[0] = True  # the clean observation is always one candidate
    dropped = policy.condition(policy.point_features(cloud).expand(n, -1, -1, -1), agent_pos.expand(n, -1, -1), keep)
    same_noise = torch.randn(1, policy.config.horizon, policy.action_dim, generator=g).expand(n, -1, -1)
    return {
        "noise_only": policy.sample(cond.expand(n, -1), g),
        "dropout_fresh_noise": policy.sample(dropped, g),
        "dropout_same_noise": policy.sample(dropped, noise=same_noise),
    }


@torch.no_grad()
def main(argv: list[str]) -> None:
    cfg = parse_config(Config, argv)
    torch.set_num_threads(cfg.threads)
    rows = []
    for path in cfg.checkpoints:
        policy = load_policy(path)
        demos = TrajectoryDataset.load(Path(cfg.data) / policy.task / "demos", task=policy.task)
        windows = TrajectoryWindows(demos, policy.config.obs_steps, policy.config.horizon)
        spread = torch.linspace(0, len(windows) - 1, cfg.observations).long().tolist()
        observations = [
            (w[keys.POINT_CLOUD], w[keys.AGENT_POS]) for w in (windows[[i]] for i in spread)
        ]  # [1, To, N, 3], [1, To, D]
        cloud, agent_pos = observations[0]
        steps_to_time = cfg.nfe if policy.config.kind == "fm" else [policy.config.ddim_steps]
        for steps in steps_to_time:
            policy.config.euler_steps = policy.config.ddim_steps = steps
            g = torch.Generator().manual_seed(cfg.seed)
            n = cfg.candidates
            cond1 = policy.encode(cloud, agent_pos)
            row = {
                "checkpoint": path,
                "kind": policy.config.kind,
                "steps": steps,
                "encoder_ms_batch1": median_ms(lambda: policy.encode(cloud, agent_pos), cfg.warmup, cfg.repeats),
                "generator_ms_batch1": median_ms(lambda: policy.sample(cond1, g), cfg.warmup, cfg.repeats),
                "decision_ms_batch1": median_ms(
                    lambda: policy.sample(policy.encode(cloud, agent_pos), g), cfg.warmup, cfg.repeats
                ),
                f"encoder_ms_batch{n}": median_ms(
                    lambda: policy.encode(cloud.expand(n, -1, -1, -1), agent_pos.expand(n, -1, -1)),
                    cfg.warmup,
                    cfg.repeats,
                ),
                f"generator_ms_batch{n}": median_ms(
                    lambda: policy.sample(cond1.expand(n, -1), g), cfg.warmup, cfg.repeats
                ),
            }
            # Diversity of n chunks from one observation, averaged over observations.
            chunks = [candidate_chunks(policy, c, a, n, cfg.dropout, g) for c, a in observations]
            for name in chunks[0]:
                row[f"diversity_{name}"] = sum(mean_pairwise_distance(c[name]) for c in chunks) / len(chunks)
            if cfg.plot:
                run = Path(path).parent.name  # e.g. fm_seed0: two seeds of a task draw two files
                plot_candidate_spread(
                    chunks[len(chunks) // 2],
                    Path(cfg.out).parent / f"candidates_{policy.task}_{run}_steps{steps}.png",
                    title=f"{policy.task} {run}, {steps} steps\n{n} chunks from one observation",
                )
            rows.append(row)
            print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
    atomic_write(cfg.out, json.dumps(rows, indent=1))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
