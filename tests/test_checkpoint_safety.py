"""Loading a checkpoint builds tensors and plain values only: a planted pickled object is refused, never run."""

import dataclasses
import json
import pathlib
import re
import runpy
import sys

import pytest
import torch

from torchrl_dalir import RerankingActor
from torchrl_dalir.checkpoints import (
    UnsafeFileError,
    load_checkpoint,
    load_policy,
    load_world_model,
    safe_torch_load,
    training_finished,
)
from torchrl_dalir.experts.adroit_pen import DEFAULT_WEIGHTS, PenExpertPolicy
from torchrl_dalir.training import train_policy

EXAMPLES = pathlib.Path(__file__).parents[1] / "examples"


class Planted:
    """Unpickling it creates ``marker``: stands for any code an attacker would run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def plant(checkpoint, out):
    """A copy at ``out`` of a real checkpoint with one more entry, whose unpickling creates ``<out>.marker``."""
    marker = out.with_suffix(".marker")
    torch.save({**safe_torch_load(checkpoint), "extra": Planted(marker)}, out)
    return out, marker


def test_the_planted_entry_runs_code_when_unpickled(trained_policy, tmp_path):
    """The attack the other tests defend against is real: ``weights_only=False`` runs it."""
    crafted, marker = plant(trained_policy[1], tmp_path / "crafted.pt")
    torch.load(crafted, weights_only=False)
    assert marker.exists()


def test_every_loader_refuses_a_planted_entry_and_never_runs_it(
    trained_policy, trained_world_model, tmp_path, monkeypatch
):
    cfg, policy_path = trained_policy
    _, wm_path, _ = trained_world_model
    policy, policy_marker = plant(policy_path, tmp_path / "policy.pt")
    world_model, wm_marker = plant(wm_path, tmp_path / "world_model.pt")
    expert, expert_marker = plant(DEFAULT_WEIGHTS, tmp_path / "pen_expert.pt")
    refusals = {
        "load_policy": lambda: load_policy(policy),
        "load_world_model": lambda: load_world_model(world_model),
        "load_checkpoint": lambda: load_checkpoint(policy, "world_model"),  # refused before the kind check
        "training_finished": lambda: training_finished(policy),
        "from_checkpoints(policy)": lambda: RerankingActor.from_checkpoints(policy, wm_path),
        "from_checkpoints(world model)": lambda: RerankingActor.from_checkpoints(policy_path, world_model),
        "PenExpertPolicy.load": lambda: PenExpertPolicy.load(expert),
    }
    for name, load in refusals.items():
        with pytest.raises(
            UnsafeFileError, match=f"refused to load {re.escape(str(tmp_path))}.*pickled io.open"
        ) as error:
            load()
        assert "weights_only=False" not in str(error.value), name  # torch's advice to run the file is not passed on
    # resuming a training run from a planted checkpoint.pt
    resumed = dataclasses.replace(cfg, out=str(tmp_path / "resumed"))
    resumed.run_dir().mkdir(parents=True)
    plant(policy_path, resumed.run_dir() / "checkpoint.pt")
    with pytest.raises(UnsafeFileError, match="checkpoint.pt"):
        train_policy(resumed)
    # examples/evaluate.py
    monkeypatch.setattr(
        sys, "argv", ["evaluate.py", f"policy_checkpoint={policy}", f"world_model={wm_path}", f"out={tmp_path}"]
    )
    with pytest.raises(UnsafeFileError, match="policy.pt"):
        runpy.run_path(str(EXAMPLES / "evaluate.py"), run_name="__main__")
    assert not any(
        marker.exists() for marker in (policy_marker, wm_marker, expert_marker, resumed.run_dir() / "checkpoint.marker")
    )


def test_an_object_of_an_older_format_asks_to_retrain(trained_world_model, tmp_path):
    _, wm_path, _ = trained_world_model
    old = tmp_path / "old.pt"
    torch.save({**safe_torch_load(wm_path), "policy_checkpoint": pathlib.Path("policy.pt")}, old)
    with pytest.raises(UnsafeFileError, match=f"{re.escape(str(old))}: it holds a pickled pathlib.PosixPath.*retrain"):
        load_world_model(old)


def test_a_file_that_is_no_checkpoint_is_named_in_the_error(trained_policy, tmp_path):
    _, policy_path = trained_policy
    data = policy_path.read_bytes()
    files = {
        "truncated.pt": data[: len(data) // 2],
        "empty.pt": b"",
        "meta.json": json.dumps({"kind": "policy"}).encode(),
    }
    for name, content in files.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ValueError, match=f"{re.escape(str(path))} is not a torch file, or is truncated") as error:
            safe_torch_load(path)
        assert not isinstance(error.value, UnsafeFileError), name
        with pytest.raises(ValueError, match=f"{re.escape(str(path))} is not a torch file, or is truncated: .+"):
            training_finished(path)
        with pytest.raises(
            ValueError, match=f"{re.escape(str(path))} is not a torchrl_dalir policy checkpoint, or is truncated"
        ):
            load_policy(path)


def test_every_checkpoint_the_library_writes_loads_safely_with_the_same_weights(trained_policy, trained_world_model):
    _, policy_path = trained_policy
    _, wm_path, _ = trained_world_model
    written = sorted(policy_path.parent.glob("*.pt")) + sorted(wm_path.parent.glob("*.pt"))
    assert {p.name for p in written} == {"checkpoint.pt", "scorer.pt", "dynamics.pt", "ensemble.pt", "world_model.pt"}
    for path in written:
        safe, unrestricted = safe_torch_load(path), torch.load(path, map_location="cpu", weights_only=False)
        assert safe.keys() == unrestricted.keys(), path
    assert training_finished(policy_path) and training_finished(wm_path.parent / "ensemble.pt")
    stored = torch.load(policy_path, map_location="cpu", weights_only=False)["policy_state"]
    for name, value in load_policy(policy_path).state_dict().items():
        assert torch.equal(value, stored[name]), name
    stored = torch.load(wm_path, map_location="cpu", weights_only=False)
    parts = load_world_model(wm_path)
    for part in ("encoder", "scorer", "world_model", "ensemble"):
        for name, value in getattr(parts, part).state_dict().items():
            assert torch.equal(value, stored[f"{part}_state"][name]), (part, name)
