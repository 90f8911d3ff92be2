"""One TorchRL ``LossModule`` per model."""

from torchrl_dalir.objectives.diffusion import DiffusionLoss
from torchrl_dalir.objectives.flow_matching import FlowMatchingLoss

__all__ = ["DiffusionLoss", "FlowMatchingLoss"]
