"""Checkpoints: the one home for writing and reading the library's files of weights.

Training writes them and inference reads them, so neither depends on the other: a
:class:`~torchrl_dalir.reranking.RerankingActor` is built from checkpoints without the training code.
"""

from torchrl_dalir.checkpoints.chunk_critic import CRITIC_ENTRIES, load_chunk_critic, save_chunk_critic
from torchrl_dalir.checkpoints.files import (
    UnsafeFileError,
    check_entries,
    load_checkpoint,
    load_weights,
    safe_torch_load,
    save_checkpoint,
    training_finished,
)
from torchrl_dalir.checkpoints.policy import POLICY_ENTRIES, load_policy, policy_entries
from torchrl_dalir.checkpoints.world_model import (
    WORLD_MODEL_ENTRIES,
    WorldModelCheckpoint,
    check_trained_on,
    load_world_model,
    save_world_model,
    store_selection,
)

__all__ = [
    "CRITIC_ENTRIES",
    "POLICY_ENTRIES",
    "UnsafeFileError",
    "WORLD_MODEL_ENTRIES",
    "WorldModelCheckpoint",
    "check_entries",
    "check_trained_on",
    "load_checkpoint",
    "load_chunk_critic",
    "load_policy",
    "load_weights",
    "load_world_model",
    "policy_entries",
    "safe_torch_load",
    "save_checkpoint",
    "save_chunk_critic",
    "save_world_model",
    "store_selection",
    "training_finished",
]
