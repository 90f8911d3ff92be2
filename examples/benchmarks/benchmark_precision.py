"""A base-policy training step in fp32 and under bf16 autocast, side by side, and what ``precision=auto`` picks.

    python examples/benchmarks/benchmark_precision.py                 # cpu-preset FM policy, batch 64 x 2 x 512 points
    python examples/benchmarks/benchmark_precision.py threads=1 repeats=20

Forward + backward + AdamW step on random inputs of the ``cpu`` preset's sizes, the two
precisions interleaved (so a busy machine slows both alike); prints the median seconds per step
of each and their ratio. On CPUs without native bf16 (AVX2 only) autocast is emulated and many
times slower: there ``precision=auto`` trains in fp32.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.modules import PolicyConfig, make_policy
from torchrl_dalir.objectives import FlowMatchingLoss
from torchrl_dalir.training.precision import autocast_dtype, native_bf16
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    batch_size: int = 64
    num_points: int = 512
    down_dims: tuple[int, ...] = (64, 128, 256)  # the cpu preset's U-Net
    warmup: int = 2
    repeats: int = 10
    threads: int = 2
    out: str = "outputs/benchmarks/precision.json"


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(0)
    policy = make_policy(PolicyConfig(down_dims=list(cfg.down_dims)), action_dim=4, state_dim=4)
    policy.fit_normalizers(torch.rand(100, 3), torch.rand(100, 4), torch.rand(100, 4))
    loss_module = FlowMatchingLoss(policy)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-4)
    batch = TensorDict(
        {
            keys.POINT_CLOUD: torch.rand(cfg.batch_size, 2, cfg.num_points, 3),
            keys.AGENT_POS: torch.rand(cfg.batch_size, 2, 4),
            keys.ACTION_CHUNK: torch.rand(cfg.batch_size, 16, 4),
        },
        [cfg.batch_size],
    )

    def step(dtype) -> float:
        start = time.perf_counter()
        with torch.autocast("cpu", dtype=dtype, enabled=dtype is not None):
            loss = loss_module(batch)["loss_flow_matching"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return time.perf_counter() - start

    precisions = {"fp32": None, "bf16": torch.bfloat16}
    seconds = {name: [] for name in precisions}
    for i in range(cfg.warmup + cfg.repeats):
        for name, dtype in precisions.items():
            value = step(dtype)
            if i >= cfg.warmup:
                seconds[name].append(value)
    medians = {name: statistics.median(values) for name, values in seconds.items()}
    auto = autocast_dtype("auto", "cpu")
    result = {
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "native_bf16": native_bf16("cpu"),
        "auto_picks": "bf16" if auto is not None else "fp32",
        "median_seconds": medians,
        "bf16_over_fp32": medians["bf16"] / medians["fp32"],
        "config": config_dict(cfg),
    }
    print(
        f"CPU capability {result['cpu_capability']}, native bf16: {result['native_bf16']}; "
        f"precision=auto picks {result['auto_picks']}"
    )
    for name, value in medians.items():
        print(f"{name}: {value:.3f} s per training step (median of {cfg.repeats})")
    print(f"bf16 / fp32: {result['bf16_over_fp32']:.2f}x")
    atomic_write(Path(cfg.out), json.dumps(result, indent=1))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
