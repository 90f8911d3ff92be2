"""Collection throughput with point clouds, per backend and worker count.

    python examples/benchmarks/benchmark_collection.py task=disassemble trajectories=40 workers=[1,2]
    python examples/benchmarks/benchmark_collection.py task=disassemble trajectories=40 \\
        workers=[1,2] backends=[local,ray]

Collects the same noisy-expert trajectories once per backend and worker count into a scratch
directory (the same rows every time) and prints env steps per second: kept trajectories' steps over
the collection's wall time, process start-up included (with ``ray``, a local Ray instance starts
unless ``ray_address`` names a cluster), and over the time after the collector was built
(``collecting_s``: without starting the worker processes, which a collection pays once per
chunk; their shutdown is still in it).
"""

from __future__ import annotations

import itertools
import json
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import check_choice, parse_config
from torchrl_dalir.data import Source, collect
from torchrl_dalir.data.collection import BACKENDS
from torchrl_dalir.utils import atomic_write


@dataclass
class Config:
    task: str = "disassemble"
    trajectories: int = 40
    noise_scale: float = 0.1
    workers: list[int] = field(default_factory=lambda: [1, 2])
    backends: list[str] = field(default_factory=lambda: ["local"])
    ray_address: str = ""  # with ray: the cluster to join; "" starts a local instance
    out: str = "outputs/benchmarks"

    def __post_init__(self):
        for backend in self.backends:
            check_choice("backends", backend, BACKENDS)


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    rows = []
    # a local Ray instance gets a CPU per actor, as the local backend starts a process per worker
    ray_init_config = (
        {"address": cfg.ray_address} if cfg.ray_address else {"num_cpus": max(cfg.workers), "include_dashboard": False}
    )
    for backend, workers in itertools.product(cfg.backends, cfg.workers):
        scratch = Path(tempfile.mkdtemp(prefix="dalir_bench_"))
        try:
            start = time.perf_counter()
            dataset = collect(
                cfg.task,
                scratch,
                [Source("noisy_expert", cfg.trajectories, noise_scale=cfg.noise_scale)],
                num_workers=workers,
                chunk_size=cfg.trajectories,
                progress=False,
                backend=backend,
                ray_init_config=ray_init_config,
            )
            seconds = time.perf_counter() - start
            steps = sum(s["env_steps"] for s in dataset.meta.shards)
            collecting = sum(s["seconds"] for s in dataset.meta.shards)
            size = sum(f.stat().st_size for f in (scratch / "rows").rglob("*") if f.is_file())
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
        rows.append(
            {
                "backend": backend,
                "workers": workers,
                "env_steps": steps,
                "seconds": round(seconds, 1),
                "steps_per_s": round(steps / seconds, 1),
                "collecting_s": round(collecting, 1),
                "collecting_steps_per_s": round(steps / collecting, 1),
                "trajectories": cfg.trajectories,
                "bytes_per_trajectory": size // cfg.trajectories,
            }
        )
        print(
            f"{cfg.task}: {backend}, {workers} worker(s): {steps} env steps in {seconds:.1f} s "
            f"= {steps / seconds:.0f} steps/s "
            f"({steps / collecting:.0f} steps/s after {seconds - collecting:.1f} s of start-up); "
            f"{size / cfg.trajectories / 2**20:.2f} MiB per trajectory on disk",
            flush=True,
        )
    atomic_write(Path(cfg.out) / f"collection_{cfg.task}.json", json.dumps(rows, indent=1))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
