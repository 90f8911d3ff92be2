"""Collect expert demos and mixed-quality trajectories for one task.

    python examples/collect_data.py task=disassemble preset=cpu
    python examples/collect_data.py task=shelf-place preset=paper num_workers=2 out=outputs/data
    python examples/collect_data.py task=shelf-place preset=paper backend=ray ray_address=auto num_workers=32

The data are the same whatever ``backend`` and ``num_workers`` (``backend=ray`` needs
``pip install "torchrl_dalir[ray]"``; ``ray_address=auto`` joins the cluster of ``ray start``).

Writes ``<out>/<task>/demos`` and ``<out>/<task>/mixed`` (TorchRL memory-mapped datasets) and
prints what they hold. Re-running loads finished datasets and resumes unfinished ones.
"""

from __future__ import annotations

import sys
import time

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import parse_config
from torchrl_dalir.data import Source, TrajectoryDataset, collect
from torchrl_dalir.data.config import PRESETS, CollectionConfig


def describe(name: str, dataset: TrajectoryDataset, seconds: float) -> None:
    steps = sum(s["env_steps"] for s in dataset.meta.shards)
    collect_seconds = sum(s["seconds"] for s in dataset.meta.shards)
    failures = sum(s.get("failures_dropped", 0) for s in dataset.meta.shards)
    labels = dataset.terminal_labels()
    print(
        f"{name}: {dataset.num_trajectories} trajectories, {len(dataset.rows)} rows, "
        f"success share {labels.mean().item():.1%}, quality {dataset.quality_counts()}, "
        f"failed attempts dropped {failures}; {steps} env steps in {collect_seconds:.0f} s of collection "
        f"({steps / max(collect_seconds, 1e-9):.0f} steps/s); this run {seconds:.0f} s; at {dataset.root}"
    )


def main(argv: list[str]) -> None:
    cfg = parse_config(CollectionConfig, argv, PRESETS)
    common = cfg.collection_kwargs()
    if cfg.stage in ("demos", "all"):
        start = time.perf_counter()
        demos = collect(
            cfg.task,
            cfg.demos_dir(),
            [Source("expert", cfg.num_demos)],
            seed=2 * cfg.seed,
            successes_only=True,
            **common,
        )
        describe("demos", demos, time.perf_counter() - start)
    if cfg.stage in ("mixed", "all"):
        start = time.perf_counter()
        mixed = collect(
            cfg.task,
            cfg.mixed_dir(),
            cfg.mixed_sources(),
            seed=2 * cfg.seed + 1,
            noise_correlation=cfg.noise_correlation,
            **common,
        )
        describe("mixed", mixed, time.perf_counter() - start)


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
