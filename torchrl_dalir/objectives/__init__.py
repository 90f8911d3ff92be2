"""One TorchRL ``LossModule`` per model."""

from torchrl_dalir.objectives.consistency_flow_matching import ConsistencyFlowMatchingLoss
from torchrl_dalir.objectives.diffusion import DiffusionLoss
from torchrl_dalir.objectives.flow_matching import FlowMatchingLoss
from torchrl_dalir.objectives.imagined_completion import ImaginedCompletionLoss
from torchrl_dalir.objectives.latent_dynamics import LatentDynamicsLoss
from torchrl_dalir.objectives.task_completion import TaskCompletionLoss

__all__ = ["ConsistencyFlowMatchingLoss", "DiffusionLoss", "FlowMatchingLoss", "ImaginedCompletionLoss", "LatentDynamicsLoss", "TaskCompletionLoss"]
