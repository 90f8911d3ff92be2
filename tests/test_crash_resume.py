"""A crash at any point resumes to the same results (issue 15): the world-model stage, interrupted in each of its
trainings, and the comparison that ``examples/maintainer/crash_trials.py`` applies to whole kill -9 trials of
the main job."""

import dataclasses
import json
import runpy
from pathlib import Path

import pytest
import torch

TRIALS = runpy.run_path(str(Path(__file__).resolve().parents[1] / "examples" / "maintainer" / "crash_trials.py"))


def test_world_model_killed_in_each_of_its_trainings_resumes_to_the_same_checkpoint(
    trained_world_model, tmp_path, monkeypatch
):
    """Killed right after the first checkpoint of the scorer's, the world model's and the ensemble's training in
    turn (each resume in a process whose random state is something else), the stage ends with the checkpoint of
    an uninterrupted run, bit for bit."""
    from torchrl_dalir.training import loop, train_world_model

    cfg, straight, _ = trained_world_model
    resumed_cfg = dataclasses.replace(cfg, out=str(tmp_path / "resumed"))
    save = loop.save_checkpoint
    for name in ("scorer", "dynamics", "ensemble"):

        def save_then_crash(path, payload, name=name):
            save(path, payload)
            if Path(path).name == f"{name}.pt":
                raise KeyboardInterrupt

        monkeypatch.setattr(loop, "save_checkpoint", save_then_crash)
        torch.manual_seed(len(name))  # whatever ran before in the process
        with pytest.raises(KeyboardInterrupt):
            train_world_model(resumed_cfg)
        assert torch.load(resumed_cfg.run_dir() / f"{name}.pt", weights_only=True)["step"] == cfg.checkpoint_every
    monkeypatch.setattr(loop, "save_checkpoint", save)
    resumed = train_world_model(resumed_cfg)
    expected, got = (
        TRIALS["load_artifact"](path, Path(root)) for path, root in ((straight, cfg.out), (resumed, resumed_cfg.out))
    )
    assert TRIALS["differences"](expected, got) == []


def test_the_trials_comparison_finds_what_differs_and_ignores_wall_times_and_the_runs_folder(tmp_path):
    runs = {}
    for name, value in (("reference", 1.0), ("trial", 2.0)):
        root = tmp_path / name
        (root / "results").mkdir(parents=True)
        result = {"success": {"records": [True, False], "seconds": value}, "config": {"out": str(root)}}
        (root / "results" / "results.json").write_text(json.dumps(result))
        torch.save({"weights": torch.tensor([0.5, value]), "path": str(root / "x.pt")}, root / "results" / "model.pt")
        runs[name] = root
    assert TRIALS["compare_runs"](runs["reference"], runs["trial"]) == {
        "results/model.pt": ["/weights: 1 of 2 rows differ"]
    }
    (runs["trial"] / "results" / "results.json").unlink()
    assert TRIALS["compare_runs"](runs["reference"], runs["trial"])["results/results.json"] == [
        "missing from the trial"
    ]
