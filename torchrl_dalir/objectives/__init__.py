"""One TorchRL ``LossModule`` per model, all on :class:`KeyedLossModule` (TorchRL's ``set_keys`` contract)."""

from torchrl_dalir.objectives.chunk_generation import ChunkGenerationLoss
from torchrl_dalir.objectives.common import KeyedLossModule
from torchrl_dalir.objectives.consistency_flow_matching import ConsistencyFlowMatchingLoss
from torchrl_dalir.objectives.critic_distillation import CriticDistillationLoss
from torchrl_dalir.objectives.diffusion import DiffusionLoss
from torchrl_dalir.objectives.distance_hinge import DistanceHingeLoss
from torchrl_dalir.objectives.flow_matching import FlowMatchingLoss
from torchrl_dalir.objectives.imagined_completion import ImaginedCompletionLoss
from torchrl_dalir.objectives.latent_dynamics import LatentDynamicsLoss
from torchrl_dalir.objectives.task_completion import TaskCompletionLoss
from torchrl_dalir.objectives.within_state_ranking import WithinStateRankingLoss

__all__ = [
    "ChunkGenerationLoss",
    "ConsistencyFlowMatchingLoss",
    "CriticDistillationLoss",
    "DiffusionLoss",
    "DistanceHingeLoss",
    "FlowMatchingLoss",
    "ImaginedCompletionLoss",
    "KeyedLossModule",
    "LatentDynamicsLoss",
    "TaskCompletionLoss",
    "WithinStateRankingLoss",
]
