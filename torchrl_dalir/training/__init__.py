"""Training: the generic loop (AdamW, cosine warm-up, EMA, resumable checkpoints) and per-model jobs."""

from torchrl_dalir.training.loop import OptimConfig, fit
from torchrl_dalir.training.policy import PRESETS as POLICY_PRESETS
from torchrl_dalir.training.policy import PolicyTrainingConfig, load_policy, train_policy
from torchrl_dalir.training.world_model import PRESETS as WORLD_MODEL_PRESETS
from torchrl_dalir.training.world_model import WorldModelTrainingConfig, load_world_model, train_world_model

__all__ = [
    "OptimConfig",
    "POLICY_PRESETS",
    "PolicyTrainingConfig",
    "WORLD_MODEL_PRESETS",
    "WorldModelTrainingConfig",
    "fit",
    "load_policy",
    "load_world_model",
    "train_policy",
    "train_world_model",
]
