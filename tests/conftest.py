"""Shared fixtures: a short task, synthetic trajectories, and one small collected dataset."""

from __future__ import annotations

import contextlib
import dataclasses

import pytest
import torch
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.envs import get_task

# MetaWorld "reach" with an 80-step limit: the expert succeeds in 40-60 steps and a
# still policy times out, so a dataset with both labels takes seconds to collect.
SHORT_REACH = dataclasses.replace(get_task("reach"), max_steps=80)


class StillPolicy(torch.nn.Module):
    """Writes a zero action: the arm does not move, the episode times out."""

    def forward(self, td):
        return td.set(keys.ACTION, torch.zeros(*td.batch_size, 4))


def still_policy():
    return StillPolicy()


def synthetic_trajectory(num_actions: int, success: bool, num_points: int = 8, action_dim: int = 2) -> TensorDict:
    """A trajectory in TorchRL's layout whose action at step t is [t, t] and agent_pos at t is [t]."""
    t = torch.arange(num_actions, dtype=torch.float32)
    success_flags = torch.zeros(num_actions, 1, dtype=torch.bool)
    success_flags[-1] = success
    done = torch.zeros(num_actions, 1, dtype=torch.bool)
    done[-1] = True
    return TensorDict(
        {
            keys.POINT_CLOUD: torch.randn(num_actions, num_points, 3),
            keys.AGENT_POS: t[:, None],
            keys.ACTION: t[:, None].expand(num_actions, action_dim).clone(),
            "next": {
                keys.POINT_CLOUD: torch.randn(num_actions, num_points, 3),
                keys.AGENT_POS: (t + 1)[:, None],
                keys.REWARD: torch.ones(num_actions, 1),
                keys.SUCCESS: success_flags,
                keys.DONE: done,
            },
        },
        batch_size=[num_actions],
    )


def untrained_reach_policy():
    """A tiny untrained FM policy for reach's 40-point clouds (its actions are noise, its normalizers made up)."""
    from torchrl_dalir.modules import PolicyConfig, make_policy

    torch.manual_seed(0)
    config = PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64])
    policy = make_policy(config, action_dim=4, state_dim=4, task="reach", num_points=40)
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 2 - 1)
    return policy


@pytest.fixture(autouse=True)
def _thread_count_restored():
    """Every test leaves torch's thread count as it found it: results differ in the last bits between
    thread counts, and the session-scoped models below are compared bit for bit with ones trained later."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def one_thread():
    """The test runs with one torch thread (the thread count is restored afterwards)."""
    torch.set_num_threads(1)


@contextlib.contextmanager
def killed_at_the_complete_mark():
    """Inside, writing a dataset's ``complete`` mark raises ``KeyboardInterrupt``: a kill between
    the rename of its rows and the mark."""
    from torchrl_dalir.data import storage

    write_meta = storage._write_meta

    def killed(root, meta):
        if meta.complete:
            raise KeyboardInterrupt
        write_meta(root, meta)

    storage._write_meta = killed
    try:
        yield
    finally:
        storage._write_meta = write_meta


@contextlib.contextmanager
def killed_at_source(source_index: int):
    """Inside, a collection is killed (``KeyboardInterrupt``) when it is about to collect a chunk of source
    ``source_index``: the chunks of the sources before it are stored."""
    from torchrl_dalir.data import collection

    collect_chunk = collection._collect_chunk

    def killed(spec, source, index, *args):
        if index == source_index:
            raise KeyboardInterrupt
        return collect_chunk(spec, source, index, *args)

    collection._collect_chunk = killed
    try:
        yield
    finally:
        collection._collect_chunk = collect_chunk


@pytest.fixture(scope="session")
def collected(tmp_path_factory):
    """A dataset of SHORT_REACH: 2 expert trajectories, 2 noisy ones, 1 still one (a time-out)."""
    from torchrl_dalir.data import Source, collect

    root = tmp_path_factory.mktemp("collected") / "reach"
    sources = [
        Source("expert", 2),
        Source("expert_noisy", 2, noise_scale=0.3),
        Source("still", 1, policy=still_policy, expert=False),
    ]
    return collect(
        SHORT_REACH, root, sources, seed=1, gamma=0.9, num_points=64, num_workers=1, chunk_size=2, progress=False
    )


@pytest.fixture(scope="session")
def trained_policy(collected, tmp_path_factory):
    """A smoke-preset FM policy trained on the collected dataset (as its demos)."""
    from torchrl_dalir.config import parse_config
    from torchrl_dalir.training import POLICY_PRESETS, PolicyTrainingConfig, train_policy

    data = tmp_path_factory.mktemp("data")
    (data / "reach").mkdir()
    (data / "reach" / "demos").symlink_to(collected.root)
    out = tmp_path_factory.mktemp("policies")
    cfg = parse_config(
        PolicyTrainingConfig,
        ["preset=smoke", "task=reach", f"data={data}", f"out={out}", "progress=false"],
        POLICY_PRESETS,
    )
    return cfg, train_policy(cfg)


@pytest.fixture(scope="session")
def trained_world_model(collected, trained_policy, tmp_path_factory):
    """A smoke-preset world model (with its scorer ensemble) on top of ``trained_policy``."""
    from torchrl_dalir.config import parse_config
    from torchrl_dalir.training import WORLD_MODEL_PRESETS, WorldModelTrainingConfig, train_world_model

    _, policy_path = trained_policy
    data = tmp_path_factory.mktemp("wm_data")
    (data / "reach").mkdir()
    (data / "reach" / "mixed").symlink_to(collected.root)
    out = tmp_path_factory.mktemp("world_models")
    cfg = parse_config(
        WorldModelTrainingConfig,
        [
            "preset=smoke",
            "task=reach",
            f"data={data}",
            f"out={out}",
            f"policy_checkpoint={policy_path}",
            "progress=false",
        ],
        WORLD_MODEL_PRESETS,
    )
    return cfg, train_world_model(cfg), policy_path
