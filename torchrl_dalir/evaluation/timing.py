"""Wall-clock timing for benchmarks: the median of repeated calls after a warm-up."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch


def synchronize(device: str | torch.device = "cpu") -> None:
    """Waits for the work queued on ``device`` (a CUDA device runs asynchronously: without this a
    timing measures the launch, not the work); nothing to wait for on the CPU."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def median_ms(
    fn: Callable[[], object], warmup: int = 5, repeats: int = 30, device: str | torch.device = "cpu"
) -> float:
    """Median milliseconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls, each call
    synchronised on ``device`` before and after."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        synchronize(device)
        start = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times)
