"""examples/benchmarks/benchmark_policy.py on a smoke policy: what its diversity numbers and its plot measure."""

import json
import runpy
import sys
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "benchmarks" / "benchmark_policy.py"


def test_mean_pairwise_distance_is_the_mean_over_ordered_pairs():
    benchmark = runpy.run_path(str(SCRIPT))
    chunks = torch.tensor([[0.0, 0.0], [3.0, 4.0], [0.0, 0.0]]).reshape(3, 1, 2)  # distances 5, 0, 5
    assert benchmark["mean_pairwise_distance"](chunks) == pytest.approx(10 / 3)


def test_benchmark_writes_latency_diversity_and_the_candidate_plot(trained_policy, tmp_path, monkeypatch, one_thread):
    cfg, policy_path = trained_policy
    out = tmp_path / "policy.json"
    args = [
        f"checkpoints=[{policy_path}]",
        f"data={cfg.data}",
        "nfe=[1,2]",
        "candidates=4",
        "observations=2",
        "dropout=0",
        "warmup=0",
        "repeats=1",
        "threads=1",
        f"out={out}",
    ]
    monkeypatch.setattr(sys, "argv", ["x", *args])
    runpy.run_path(str(SCRIPT), run_name="__main__")
    rows = json.loads(out.read_text())
    assert [(row["kind"], row["steps"]) for row in rows] == [("fm", 1), ("fm", 2)] and rows[0]["decision_ms_batch1"] > 0
    for (
        row
    ) in rows:  # without dropout every candidate sees the clean cloud: with the same noise the chunks are one chunk
        assert row["diversity_dropout_same_noise"] == 0.0 and row["diversity_noise_only"] > 0
    run = Path(policy_path).parent.name
    assert all((tmp_path / f"candidates_reach_{run}_steps{steps}.png").stat().st_size > 0 for steps in (1, 2))
