"""Milliseconds per decision of the base policies alone and with DALI-R (the paper's Table 5).

    python examples/benchmarks/benchmark_latency.py preset=cpu candidates=[1,4,8,16,32]
    python examples/benchmarks/benchmark_latency.py kinds=[fm] candidates=[32] \\
        precisions=[fp32,bf16]  # bf16 autocast at inference

Builds FM and DP policies and a latent world model and scorer with the ``preset``'s architectures
(untrained: latency does not depend on the weights), then times full decisions on one observation of
``num_points`` points on ``device`` (:func:`torchrl_dalir.evaluation.latency.measure_latency`): median of
``repeats`` decisions after ``warmup``, all in one process. The table gives each time and its ratio to the
base policy alone (the issue's goals: FM + DALI-R at 32 candidates at most 3x FM, DP + DALI-R at most 2x
DP). ``precisions=[fp32,bf16]`` times every decision under each precision (bf16: autocast, as training's
``precision=bf16``), one row per backbone and precision.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass

import torch

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.evaluation.latency import LatencyConfig, latency_table, measure_latency
from torchrl_dalir.utils import atomic_write


@dataclass
class Config(LatencyConfig):
    threads: int = 2
    out: str = "outputs/benchmarks/latency.json"


def main(argv: list[str]) -> None:
    cfg = parse_config(Config, argv)
    torch.set_num_threads(cfg.threads)
    rows = measure_latency(cfg)
    for row in rows:
        print(json.dumps(row), flush=True)
    lines = latency_table(rows, cfg.candidates)
    print("\n".join(lines))
    atomic_write(cfg.out, json.dumps({"config": config_dict(cfg), "rows": rows, "table": lines}, indent=1))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
