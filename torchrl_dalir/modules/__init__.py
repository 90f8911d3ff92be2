"""Networks: observation encoders, the conditional U-Net, and the base 3D policies."""

from torchrl_dalir.modules.chunk_critic import ChunkCritic
from torchrl_dalir.modules.config import PolicyConfig
from torchrl_dalir.modules.encoders import PointCloudEncoder, StateEncoder
from torchrl_dalir.modules.normalizer import MinMaxNormalizer
from torchrl_dalir.modules.point_cloud_critic import PointCloudCritic, PointCloudCriticModule
from torchrl_dalir.modules.policies import ChunkPolicy3D, DiffusionPolicy3D, FlowMatchingPolicy3D, make_policy
from torchrl_dalir.modules.policy_interface import ChunkPolicy
from torchrl_dalir.modules.unet import ConditionalUnet1D
from torchrl_dalir.modules.world_model import (
    LatentEncoder,
    LatentEncoderModule,
    LatentWorldModel,
    ScorerEnsemble,
    ScorerEnsembleModule,
    ScorerModule,
    TaskCompletionScorer,
    WorldModelModule,
)

__all__ = [
    "ChunkCritic",
    "ChunkPolicy",
    "ChunkPolicy3D",
    "ConditionalUnet1D",
    "DiffusionPolicy3D",
    "FlowMatchingPolicy3D",
    "LatentEncoder",
    "LatentEncoderModule",
    "LatentWorldModel",
    "MinMaxNormalizer",
    "PointCloudCritic",
    "PointCloudCriticModule",
    "PointCloudEncoder",
    "PolicyConfig",
    "ScorerEnsemble",
    "ScorerEnsembleModule",
    "ScorerModule",
    "StateEncoder",
    "TaskCompletionScorer",
    "WorldModelModule",
    "make_policy",
]
