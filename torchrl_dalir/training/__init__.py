"""Training: the generic loop (AdamW, cosine warm-up, EMA, resumable checkpoints) and per-model jobs."""

from torchrl_dalir.training.loop import OptimConfig, fit
from torchrl_dalir.training.policy import PRESETS as POLICY_PRESETS
from torchrl_dalir.training.policy import PolicyTrainingConfig, load_policy, train_policy

__all__ = ["OptimConfig", "POLICY_PRESETS", "PolicyTrainingConfig", "fit", "load_policy", "train_policy"]
