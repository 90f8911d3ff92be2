"""torchrl_dalir: DALI-R (data-asymmetric latent imagination and reranking) on TorchRL."""

import os

# Offscreen MuJoCo rendering on the CPU (Mesa EGL); a user's own setting wins.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from torchrl_dalir import keys  # noqa: E402
from torchrl_dalir.envs import TASKS, get_task, make_env  # noqa: E402

__version__ = "0.3.0"  #: The package's version (as in ``pyproject.toml``).

from torchrl_dalir.modules import DiffusionPolicy3D, FlowMatchingPolicy3D, LatentWorldModel, TaskCompletionScorer  # noqa: E402
from torchrl_dalir.modules.policy_interface import ChunkPolicy  # noqa: E402
from torchrl_dalir.modules.receding_horizon import receding_horizon  # noqa: E402
from torchrl_dalir.reranking import (  # noqa: E402
    GaussianObservationNoise,
    PointDropout,
    RerankingActor,
    RerankingConfig,
    SearchConfig,
    SelectionConfig,
)

__all__ = [
    "TASKS",
    "ChunkPolicy",
    "DiffusionPolicy3D",
    "FlowMatchingPolicy3D",
    "GaussianObservationNoise",
    "LatentWorldModel",
    "PointDropout",
    "RerankingActor",
    "RerankingConfig",
    "SearchConfig",
    "SelectionConfig",
    "TaskCompletionScorer",
    "__version__",
    "get_task",
    "keys",
    "make_env",
    "receding_horizon",
]
