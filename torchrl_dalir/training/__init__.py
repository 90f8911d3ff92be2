"""Training: the generic loop (AdamW, cosine warm-up, EMA, resumable checkpoints) and per-model jobs.

``load_policy`` and ``load_world_model`` live in :mod:`torchrl_dalir.checkpoints`; they stay
importable from here for existing code.
"""

from torchrl_dalir.checkpoints import load_policy, load_world_model
from torchrl_dalir.training import distributed
from torchrl_dalir.training.loop import OptimConfig, fit
from torchrl_dalir.training.policy import PRESETS as POLICY_PRESETS
from torchrl_dalir.training.policy import PolicyTrainingConfig, train_policy
from torchrl_dalir.training.world_model import PRESETS as WORLD_MODEL_PRESETS
from torchrl_dalir.training.world_model import WorldModelTrainingConfig, train_world_model

__all__ = [
    "OptimConfig",
    "POLICY_PRESETS",
    "PolicyTrainingConfig",
    "WORLD_MODEL_PRESETS",
    "WorldModelTrainingConfig",
    "distributed",
    "fit",
    "load_policy",
    "load_world_model",
    "train_policy",
    "train_world_model",
]
