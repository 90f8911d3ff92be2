import json
import runpy
import sys
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run_example(name, args, monkeypatch):
    monkeypatch.setattr(sys, "argv", [name, *args])
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")


@pytest.mark.parametrize("policy", ["fm"])
def test_main_job_smoke_runs_every_stage_and_skips_them_next_time(tmp_path, monkeypatch, capsys, policy):
    args = ["preset=smoke", "task=reach", f"policy={policy}", f"out={tmp_path}", "collection.progress=false",
            "policy_training.progress=false", "world_model.progress=false"]
    run_example("train_dp3_wm.py", args, monkeypatch)
    results = tmp_path / "results" / "reach" / f"{policy}_seed0"
    data = json.loads((results / "results.json").read_text())
    assert set(data["success"]) == {"base policy", "DALI-R"}
    assert all(len(r["records"]) == 2 for r in data["success"].values())
    assert (results / "imagination.png").stat().st_size > 0
    assert "| + DALI-R" in (results / "results.md").read_text()
    capsys.readouterr()
    run_example("train_dp3_wm.py", args, monkeypatch)
    assert capsys.readouterr().out.count("done before") == 5
    # an interrupted policy training (its checkpoint short of the last step) is resumed, not skipped
    checkpoint = tmp_path / "policies" / "reach" / f"{policy}_seed0" / "checkpoint.pt"
    state = torch.load(checkpoint, weights_only=False)
    state["step"] -= 1
    torch.save(state, checkpoint)
    run_example("train_dp3_wm.py", args, monkeypatch)
    out = capsys.readouterr().out
    assert "[policy] done before" not in out and out.count("done before") == 4
    assert torch.load(checkpoint, weights_only=False)["step"] == state["num_steps"]
