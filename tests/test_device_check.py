"""examples/benchmarks/device_check.py at smoke size on the CPU: every part runs, the CPU agrees with itself bit
for bit, a failing part is recorded without stopping the others, and a missing GPU is refused by name."""

import json
import runpy
import sys
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "benchmarks" / "device_check.py"


def run_check(args, monkeypatch):
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *args])
    runpy.run_path(str(SCRIPT), run_name="__main__")


def test_device_check_smoke_on_cpu_runs_every_part_and_records_a_failing_one(tmp_path, monkeypatch, capsys):
    args = ["preset=smoke", "device=cpu", f"out={tmp_path}"]
    run_check(args, monkeypatch)
    result = json.loads((tmp_path / "device_check.json").read_text())
    assert result["failed"] == []
    assert set(result["main_job"]["stage_seconds"]) == {"demos", "policy", "mixed", "world_model"}
    rows = result["latency"]["rows"]
    assert [(r["architecture"], r["kind"], r["precision"]) for r in rows] == [
        ("smoke", "fm", "fp32"),
        ("smoke", "dp", "fp32"),
    ]
    assert all(r["dalir_1_ms"] > 0 and r["dalir_2_ms"] > 0 for r in rows)
    assert len(result["latency"]["table"]) == 5  # header, rule, base policy, 1 and 2 candidates
    agreement = result["agreement"]
    assert agreement["max_action_difference"] == 0.0 and agreement["max_score_difference"] == 0.0
    assert agreement["same_choice"] == agreement["decisions"] == 3 and agreement["passed"]

    # a part that fails is recorded, the others still run (the finished main job is reused), and the command fails
    def broken(cfg):
        raise RuntimeError("kernel not available")

    monkeypatch.setattr("torchrl_dalir.evaluation.latency.measure_latency", broken)
    with pytest.raises(SystemExit) as exit_code:
        run_check([*args, "json=" + str(tmp_path / "broken.json")], monkeypatch)
    assert exit_code.value.code == 1
    broken_result = json.loads((tmp_path / "broken.json").read_text())
    assert broken_result["failed"] == ["latency"]
    assert "kernel not available" in broken_result["latency"]["error"]
    assert broken_result["agreement"]["passed"]
    assert "FAILED: latency" in capsys.readouterr().out


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_device_check_refuses_cuda_without_a_gpu(monkeypatch, tmp_path):
    with pytest.raises(RuntimeError, match="sees no CUDA device"):
        run_check(["device=cuda", f"out={tmp_path}"], monkeypatch)
