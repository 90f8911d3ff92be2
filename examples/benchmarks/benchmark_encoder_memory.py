"""Peak memory and page faults of the world-model stage's encoder pass (``encode_rows``).

    python examples/benchmarks/benchmark_encoder_memory.py  # under the malloc tunables (the default)
    DALIR_MALLOC=system python examples/benchmarks/benchmark_encoder_memory.py   # glibc's malloc defaults

The latent encoder of a ``cpu``-preset policy (untrained: memory depends on sizes, not values)
encodes ``rows`` random 512-point observations ``passes`` times, keeping every pass's latents as
the stage keeps its one. Prints the seconds, the process's peak resident memory and the minor page
faults of the passes. Under the tunables a heap is never trimmed; per-batch pieces kept alive
between the batches' large freed activations then make it grow with every batch, so this is the
check that the pass writes in place.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.allocator import SWITCH, reuse_freed_memory
from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.modules import make_policy
from torchrl_dalir.modules.world_model import LatentEncoder
from torchrl_dalir.training.policy import PRESETS, PolicyTrainingConfig
from torchrl_dalir.training.world_model import encode_rows
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    rows: int = 60000  # about a MetaWorld mixed dataset (DP disassemble s0: 61,801 rows)
    passes: int = 3
    num_points: int = 512
    batch_size: int = 1024  # encode_rows' default
    threads: int = 1
    out: str = "outputs/benchmarks/encoder_memory.json"


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(0)
    policy_cfg = parse_config(PolicyTrainingConfig, ["task=disassemble"], PRESETS)
    policy = make_policy(policy_cfg.resolved().model, action_dim=4, state_dim=4)
    policy.fit_normalizers(torch.rand(100, 3), torch.rand(100, 4), torch.rand(100, 4))
    encoder = LatentEncoder.from_policy(policy).eval().requires_grad_(False)
    rows = TensorDict(
        {keys.POINT_CLOUD: torch.rand(cfg.rows, cfg.num_points, 3), keys.AGENT_POS: torch.rand(cfg.rows, 4)}, [cfg.rows]
    )

    kept = []
    before = resource.getrusage(resource.RUSAGE_SELF)
    start = time.perf_counter()
    for _ in range(cfg.passes):
        kept.append(encode_rows(encoder, rows, cfg.batch_size))
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_SELF)
    result = {
        "malloc": os.environ.get(SWITCH) or "default",
        "seconds": seconds,
        "peak_rss_gib": after.ru_maxrss / 2**20,
        "peak_rss_before_gib": before.ru_maxrss / 2**20,
        "minor_faults_m": (after.ru_minflt - before.ru_minflt) / 1e6,
        "config": config_dict(cfg),
    }
    print(
        f"malloc {result['malloc']}: {cfg.passes} passes over {cfg.rows} rows in {seconds:.1f} s; peak resident memory "
        f"{result['peak_rss_gib']:.2f} GiB ({result['peak_rss_before_gib']:.2f} before the passes); "
        f"{result['minor_faults_m']:.2f} M minor page faults"
    )
    atomic_write(Path(cfg.out), json.dumps(result, indent=1))


if __name__ == "__main__":
    reuse_freed_memory(__file__)
    main(sys.argv[1:])
