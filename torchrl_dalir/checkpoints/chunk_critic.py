"""Chunk-critic checkpoints: a :class:`~torchrl_dalir.modules.ChunkCritic` (or a
:class:`~torchrl_dalir.modules.PointCloudCritic`, with encoders of its own), the policy it was trained on (a
digest of its weights) and its training run's metrics."""

from __future__ import annotations

from pathlib import Path

from torchrl_dalir.checkpoints.files import load_checkpoint, load_weights, save_checkpoint
from torchrl_dalir.modules.chunk_critic import ChunkCritic
from torchrl_dalir.modules.point_cloud_critic import PointCloudCritic
from torchrl_dalir.utils import weights_digest

#: What a chunk-critic checkpoint must hold to be loaded.
CRITIC_ENTRIES = ("architecture", "critic_state", "policy_digest", "metrics")
#: The critic classes a checkpoint may hold, by the name it stores (checkpoints without one hold a ChunkCritic).
CRITIC_CLASSES = {cls.__name__: cls for cls in (ChunkCritic, PointCloudCritic)}


def save_chunk_critic(path: str | Path, critic: ChunkCritic, policy, metrics: dict) -> None:
    """Writes ``critic`` (trained on ``policy``'s candidates) and its ``metrics`` to ``path``, atomically."""
    if type(critic).__name__ not in CRITIC_CLASSES:
        raise TypeError(f"a chunk-critic checkpoint holds one of {list(CRITIC_CLASSES)}, not {type(critic).__name__}")
    save_checkpoint(
        path,
        {
            "kind": "chunk_critic",
            "critic_class": type(critic).__name__,
            "architecture": critic.architecture(),
            "critic_state": critic.state_dict(),
            "policy_digest": weights_digest(policy),
            "metrics": metrics,
        },
    )


def load_chunk_critic(path: str | Path, device="cpu", policy=None) -> ChunkCritic:
    """The critic saved at ``path``; with ``policy``, refuses a critic trained on another policy's candidates."""
    state = load_checkpoint(path, "chunk_critic", CRITIC_ENTRIES)
    if policy is not None and state["policy_digest"] != weights_digest(policy):
        raise ValueError(
            f"{path} was trained on the candidates of another policy (weights digest "
            f"{state['policy_digest'][:12]}, not {weights_digest(policy)[:12]})"
        )
    critic = CRITIC_CLASSES[state.get("critic_class", "ChunkCritic")](**state["architecture"])
    load_weights(critic, state, "critic_state", path)
    critic.metrics = state["metrics"]
    return critic.to(device).eval()
