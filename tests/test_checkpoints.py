"""Checkpoints' one home: atomic writes, save -> load round trips, typed results, older formats still loading."""

import dataclasses
import functools
import threading
import warnings
from dataclasses import asdict

import pytest
import torch

from torchrl_dalir.checkpoints import (
    WorldModelCheckpoint,
    load_policy,
    load_world_model,
    policy_entries,
    safe_torch_load,
    save_checkpoint,
    save_world_model,
    store_selection,
)
from torchrl_dalir.checkpoints import policy as policy_checkpoints
from torchrl_dalir.modules import PolicyConfig, make_policy
from torchrl_dalir.modules.world_model import LatentEncoder, LatentWorldModel, ScorerEnsemble, TaskCompletionScorer
from torchrl_dalir.reranking.selection import SelectionConfig
from torchrl_dalir.utils import atomic_write, weights_digest

TINY = dict(down_dims=[16, 32, 64], point_hidden=[16, 32, 64], train_timesteps=20, ddim_steps=2, euler_steps=2)
LOW, HIGH = torch.full((4,), -0.5), torch.full((4,), 0.75)


def _policy(**fields):
    torch.manual_seed(0)
    policy = make_policy(PolicyConfig(kind="fm", **TINY), action_dim=4, state_dim=4, **fields)
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 2 - 1)
    return policy.eval()


def _no_simulator(monkeypatch):
    monkeypatch.setattr(
        policy_checkpoints, "action_bounds", lambda task: pytest.fail("a simulator was built for the bounds")
    )


# -- atomic writes ---------------------------------------------------------------------------------
def test_atomic_write_writes_text_bytes_and_what_a_function_writes(tmp_path):
    atomic_write(tmp_path / "a" / "text.json", '{"é": 1}')  # the folder is created
    atomic_write(tmp_path / "raw.bin", b"\x00\x01")
    atomic_write(tmp_path / "weights.pt", functools.partial(torch.save, {"w": torch.arange(3)}))
    assert (tmp_path / "a" / "text.json").read_text(encoding="utf-8") == '{"é": 1}'
    assert (tmp_path / "raw.bin").read_bytes() == b"\x00\x01"
    assert torch.equal(safe_torch_load(tmp_path / "weights.pt")["w"], torch.arange(3))


def test_a_failed_write_leaves_the_old_file_intact_and_no_temporary_file(tmp_path):
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"kind": "policy", "step": 1})

    def crash(file):
        file.write(b"half a checkpoint")
        raise KeyboardInterrupt  # killed while writing

    with pytest.raises(KeyboardInterrupt):
        atomic_write(path, crash)
    with pytest.raises(TypeError, match="cannot pickle"):  # fails inside torch.save, after it has begun writing
        save_checkpoint(path, {"kind": "policy", "step": 2, "unsaveable": threading.Lock()})
    assert safe_torch_load(path) == {"kind": "policy", "step": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]


# -- policy checkpoints ----------------------------------------------------------------------------
def test_a_policy_round_trips_with_its_weights_fields_and_bounds_without_a_simulator(tmp_path, monkeypatch):
    policy = _policy(task="reach", num_points=16)
    policy.set_action_bounds(LOW, HIGH)
    path = tmp_path / "policy.pt"
    save_checkpoint(path, policy_entries(policy, {"seed": 3}))
    _no_simulator(monkeypatch)
    loaded = load_policy(path)
    assert (loaded.task, loaded.num_points, loaded.checkpoint) == ("reach", 16, str(path))
    assert torch.equal(loaded.action_low, LOW) and torch.equal(loaded.action_high, HIGH)
    assert loaded.state_dict().keys() == policy.state_dict().keys()
    assert all(torch.equal(value, policy.state_dict()[name]) for name, value in loaded.state_dict().items())
    assert not loaded.training and safe_torch_load(path)["config"] == {"seed": 3}
    cond = policy.encode(torch.rand(2, 2, 16, 3), torch.rand(2, 2, 4))
    noise = torch.randn(2, 16, 4)
    assert torch.equal(loaded.sample(cond, noise=noise), policy.sample(cond, noise=noise))


def test_a_policy_without_its_task_or_cloud_size_is_not_saved():
    with pytest.raises(ValueError, match="build the policy with task=... and num_points=..."):
        policy_entries(_policy(task="reach"))


def test_an_older_policy_checkpoint_without_bounds_takes_its_tasks_bounds(tmp_path, monkeypatch):
    policy = _policy()
    path = tmp_path / "old.pt"  # the entries a policy checkpoint held before the bounds were stored
    torch.save(
        {
            "kind": "policy",
            "task": "reach",
            "config": {},
            "policy_config": asdict(policy.config),
            "action_dim": 4,
            "state_dim": 4,
            "num_points": 16,
            "policy_state": policy.state_dict(),
            "library_version": "0.2.0",
        },
        path,
    )
    asked = []
    monkeypatch.setattr(policy_checkpoints, "action_bounds", lambda task: asked.append(task) or (LOW, HIGH))
    loaded = load_policy(path)
    assert asked == ["reach"] and torch.equal(loaded.action_low, LOW) and torch.equal(loaded.action_high, HIGH)
    assert (loaded.task, loaded.num_points) == ("reach", 16)


# -- world-model checkpoints -----------------------------------------------------------------------
def _save_world_model(path, policy):
    encoder = LatentEncoder.from_policy(policy)
    world_model_args = dict(latent_dim=encoder.latent_dim, action_dim=4, action_steps=8, hidden=32, layers=1, heads=2)
    ensemble_args = dict(latent_dim=encoder.latent_dim, hidden=16, members=2)
    modules = dict(
        encoder=encoder,
        world_model=LatentWorldModel(**world_model_args),
        scorer=TaskCompletionScorer(encoder.latent_dim, 32),
        ensemble=ScorerEnsemble(**ensemble_args),
    )
    save_world_model(
        path,
        policy=policy,
        policy_checkpoint="policy.pt",
        world_model_args=world_model_args,
        scorer_hidden=32,
        ensemble_args=ensemble_args,
        held_out_trajectories=[2, 5],
        metrics={"wm_mse": 0.1},
        encoder_mode="frozen",
        config={"seed": 0},
        **modules,
    )
    return modules


def test_a_world_model_round_trips_as_a_typed_result(tmp_path):
    policy = _policy(task="reach", num_points=16)
    path = tmp_path / "world_model.pt"
    modules = _save_world_model(path, policy)
    parts = load_world_model(path, policy=policy)
    assert isinstance(parts, WorldModelCheckpoint)
    assert [f.name for f in dataclasses.fields(parts)] == [
        "task",
        "encoder",
        "world_model",
        "scorer",
        "ensemble",
        "selection",
        "calibration",
        "metrics",
        "policy_checkpoint",
        "policy_digest",
        "held_out_trajectories",
    ]
    assert (parts.task, parts.selection, parts.calibration, parts.metrics) == (
        "reach",
        SelectionConfig(),
        None,
        {"wm_mse": 0.1},
    )
    assert (parts.policy_checkpoint, parts.policy_digest, parts.held_out_trajectories) == (
        "policy.pt",
        weights_digest(policy),
        [2, 5],
    )
    for name, module in modules.items():
        loaded = getattr(parts, name)
        assert not loaded.training, name
        assert all(torch.equal(value, module.state_dict()[key]) for key, value in loaded.state_dict().items()), name
    assert safe_torch_load(path)["encoder_mode"] == "frozen"
    chosen = SelectionConfig("margin", "ensemble", k=1.0, margin=0.02)
    store_selection(path, chosen, {"chosen": chosen.name})
    stored = load_world_model(path)
    assert (stored.selection, stored.calibration) == (chosen, {"chosen": chosen.name})


def test_an_older_world_model_checkpoint_still_loads(tmp_path):
    policy = _policy(task="reach", num_points=16)
    path = tmp_path / "world_model.pt"
    _save_world_model(path, policy)
    state = safe_torch_load(path)
    for entry in ("ensemble_state", "ensemble_args", "selection", "policy_digest", "encoder_mode", "library_version"):
        del state[entry]  # as written before version 0.2.0
    torch.save(state, path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parts = load_world_model(path, policy=policy)
    assert any("does not record which policy" in str(w.message) for w in caught)
    assert (parts.ensemble, parts.selection, parts.policy_digest) == (None, SelectionConfig(), None)
