"""Point dropout's two paths: per-point features pooled under each mask, or each dropped cloud encoded anew.

    python examples/benchmarks/benchmark_point_dropout.py   # the cpu preset's FM architecture, 32 candidates, 1 thread
    python examples/benchmarks/benchmark_point_dropout.py kind=dp candidates=8

A policy with per-point features (``point_features`` and ``condition``, as the library's
``ChunkPolicy3D`` has) gets DALI-R's candidate conditions from one pass of its point MLP and one
pooling per candidate; any other ``ChunkPolicy`` has every dropped cloud encoded by its ``encode``
(``PointDropout.conditions``). Both give the same conditions; this times them (median
milliseconds per decision of one observation, after a warm-up), alone and with the policy's
sampling of the chunks, on the library's policy with and without its fast path (weights untrained:
the time does not depend on them). Prints one JSON line; ``out=`` also writes it.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass

import torch

from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.timing import median_ms
from torchrl_dalir.modules import PolicyConfig, make_policy
from torchrl_dalir.reranking import PointDropout, RerankingConfig
from torchrl_dalir.training import POLICY_PRESETS
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    kind: str = "fm"  # the policy's generator: fm | dp
    preset: str = "cpu"  # the policy training preset whose architecture is timed
    candidates: int = RerankingConfig.num_candidates
    dropout: float = RerankingConfig.dropout
    num_points: int = 512  # the collection's cloud size
    state_dim: int = 4  # MetaWorld's
    action_dim: int = 4
    threads: int = 1
    warmup: int = 5
    repeats: int = 30
    seed: int = 0
    out: str = ""  # a JSON file for the result ("": print only)


class EncodeOnly:
    """The policy's ``ChunkPolicy`` members without the per-point fast path."""

    def __init__(self, policy):
        self.policy = policy
        self.obs_steps, self.horizon, self.action_steps, self.action_dim = (
            policy.obs_steps,
            policy.horizon,
            policy.action_steps,
            policy.action_dim,
        )

    def encode(self, point_cloud, agent_pos):
        return self.policy.encode(point_cloud, agent_pos)

    def sample(self, cond, generator=None, noise=None):
        return self.policy.sample(cond, generator, noise)


@torch.no_grad()
def main(argv: list[str]) -> dict:
    cfg: Config = parse_config(Config, argv)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    policy = make_policy(
        PolicyConfig(**{**POLICY_PRESETS[cfg.preset].get("model", {}), "kind": cfg.kind}), cfg.action_dim, cfg.state_dim
    ).eval()
    policy.fit_normalizers(torch.rand(100, 3), torch.rand(100, cfg.state_dim), torch.rand(100, cfg.action_dim) * 2 - 1)
    cloud, agent_pos = (
        torch.rand(1, policy.obs_steps, cfg.num_points, 3),
        torch.rand(1, policy.obs_steps, cfg.state_dim),
    )
    dropout = PointDropout(cfg.dropout)
    paths = {"features": policy, "re_encode": EncodeOnly(policy)}

    def conditions(target):
        return dropout.conditions(target, cloud, agent_pos, cfg.candidates, torch.Generator().manual_seed(cfg.seed))

    difference = (conditions(paths["features"]) - conditions(paths["re_encode"])).abs().max().item()
    result = {
        "kind": cfg.kind,
        "preset": cfg.preset,
        "candidates": cfg.candidates,
        "num_points": cfg.num_points,
        "threads": cfg.threads,
        "max_abs_difference": difference,
    }
    for name, target in paths.items():
        result[f"conditions_ms_{name}"] = median_ms(lambda t=target: conditions(t), cfg.warmup, cfg.repeats)
        result[f"candidates_ms_{name}"] = median_ms(lambda t=target: t.sample(conditions(t)), cfg.warmup, cfg.repeats)
    for part in ("conditions", "candidates"):
        result[f"{part}_ratio"] = result[f"{part}_ms_re_encode"] / result[f"{part}_ms_features"]
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in result.items()}), flush=True)
    if cfg.out:
        atomic_write(cfg.out, json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
