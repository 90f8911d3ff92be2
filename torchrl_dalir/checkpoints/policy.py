"""Policy checkpoints: what a trained base policy is saved as, and loading it back.

A policy checkpoint holds the policy's architecture, its EMA weights and what it was trained on
(task, cloud size) and the action bounds of its task, so that loading it needs no simulator (a
checkpoint written before the bounds were stored is given those of its task's simulator).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from torchrl_dalir.checkpoints.files import load_checkpoint, load_weights
from torchrl_dalir.envs.make_env import action_bounds
from torchrl_dalir.modules import ChunkPolicy3D, PolicyConfig, make_policy

#: What a policy checkpoint must hold to be loaded (``action_bounds`` is optional: older ones have none).
POLICY_ENTRIES = ("task", "policy_config", "action_dim", "state_dim", "num_points", "policy_state")


def policy_entries(policy: ChunkPolicy3D, config: dict | None = None) -> dict:
    """The entries a policy checkpoint stores for ``policy`` (a training run's checkpoint adds its
    resume state to them): its architecture, weights, ``task``, ``num_points`` and action bounds.

    Args:
        policy: a policy built with its ``task`` and ``num_points`` (and its task's action bounds set).
        config: the training configuration, stored for the record.

    Example:
        >>> import tempfile
        >>> from torchrl_dalir.checkpoints import save_checkpoint
        >>> policy = make_policy(PolicyConfig(down_dims=[8, 16, 32]), 4, 4, task="reach", num_points=64)
        >>> path = Path(tempfile.mkdtemp()) / "policy.pt"
        >>> save_checkpoint(path, policy_entries(policy))
        >>> loaded = load_policy(path)
        >>> loaded.task, loaded.num_points, loaded.checkpoint == str(path)
        ('reach', 64, True)
    """
    from torchrl_dalir import __version__

    if policy.task is None or policy.num_points is None:
        raise ValueError(
            "a policy checkpoint records the task and cloud size the policy was trained on: "
            "build the policy with task=... and num_points=..."
        )
    return {
        "kind": "policy",
        "task": policy.task,
        "config": config if config is not None else {},
        "policy_config": asdict(policy.config),
        "action_dim": policy.action_dim,
        "state_dim": policy.state_dim,
        "num_points": policy.num_points,
        "policy_state": policy.state_dict(),
        "action_bounds": [policy.action_low.cpu(), policy.action_high.cpu()],
        "library_version": __version__,
    }


def load_policy(
    path: str | Path, device: str | torch.device = "cpu", task: str | None = None, **key_names
) -> ChunkPolicy3D:
    """Loads the EMA policy of a checkpoint, in eval mode, with its ``task``, ``num_points`` and
    ``checkpoint`` (``path``) and the action bounds of its task; refuses another task's policy.

    Args:
        path: a policy checkpoint (``train_policy``'s ``checkpoint.pt``).
        device: where the policy runs.
        task: the task it must have been trained on, if given.
        key_names: the policy's ``in_keys``/``out_keys`` if not the defaults.

    Example:
        >>> policy = load_policy("outputs/policies/disassemble/fm_seed0/checkpoint.pt")  # doctest: +SKIP
        >>> policy.task, policy.num_points  # doctest: +SKIP
        ('disassemble', 512)
    """
    state = load_checkpoint(path, "policy", POLICY_ENTRIES)
    if task is not None and state["task"] != task:
        raise ValueError(f"{path} holds a policy for task {state['task']!r}, not {task!r}")
    policy = make_policy(
        PolicyConfig(**state["policy_config"]),
        state["action_dim"],
        state["state_dim"],
        task=state["task"],
        num_points=state["num_points"],
        checkpoint=str(path),
        **key_names,
    )
    load_weights(policy, state, "policy_state", path)
    # its chunks hold what the env executes; an older checkpoint without the bounds asks its task's simulator (~1 s)
    policy.set_action_bounds(*state.get("action_bounds") or action_bounds(state["task"]))
    return policy.to(device).eval()
