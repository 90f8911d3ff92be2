"""The Adroit Pen expert: a PPO policy trained on the simulator state.

No Pen expert can be downloaded, so this one is trained here by ``examples/maintainer/train_pen_expert.py``
(TorchRL PPO on the state, terminating at the first success as our evaluation protocol does).
The committed weights live in ``torchrl_dalir/experts/weights/pen_expert.pt``; they include the
observation normalisation, so :class:`PenExpertPolicy` needs nothing but the privileged state.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn
from torchrl.modules import MLP

from torchrl_dalir import keys
from torchrl_dalir.checkpoints.files import safe_torch_load, save_checkpoint

OBS_DIM = 45  # AdroitHandPen-v1's observation: the leading part of the privileged state
STATE_DIM = 105  # observation (45) + qpos (30) + qvel (30), see TaskSpec.privileged_state
ACTION_DIM = 24
HIDDEN = (256, 256)
DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "pen_expert.pt"


def make_actor_mlp() -> MLP:
    """The actor's body: normalised observation -> pre-tanh action mean. Shared by the trainer
    and :class:`PenExpertPolicy` so that trained weights load without renaming."""
    return MLP(in_features=OBS_DIM, out_features=ACTION_DIM, num_cells=list(HIDDEN), activation_class=nn.Tanh)


class PenExpertPolicy(nn.Module):
    """Maps the Pen privileged state ``[..., 105]`` to the deterministic action ``[..., 24]``.

    Only the gym observation (the first 45 entries) is read; it is normalised with the
    statistics gathered during training, then the actor's mean goes through ``tanh`` (the mean
    action of PPO's ``TanhNormal`` policy), so actions lie in ``[-1, 1]``.

    Example:
        >>> expert = PenExpertPolicy.load()  # the weights shipped with the package
        >>> action = expert(torch.zeros(5, 105))
        >>> action.shape, bool(action.abs().max() <= 1)
        (torch.Size([5, 24]), True)
    """

    in_keys = [keys.PRIVILEGED_STATE]

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("obs_loc", torch.zeros(OBS_DIM))
        self.register_buffer("obs_scale", torch.ones(OBS_DIM))
        self.net = make_actor_mlp()

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        if state.shape[-1] != STATE_DIM:
            raise ValueError(
                f"PenExpertPolicy expects the Pen privileged state with {STATE_DIM} entries in its "
                f"last dimension (observation 45 + qpos 30 + qvel 30), got shape {tuple(state.shape)}"
            )
        obs = state[..., :OBS_DIM].to(self.obs_loc.dtype)
        return torch.tanh(self.net((obs - self.obs_loc) / self.obs_scale))

    @classmethod
    def load(cls, path: str | Path | None = None) -> PenExpertPolicy:
        """Loads the committed weights (or those at ``path``), in eval mode."""
        path = Path(path) if path is not None else DEFAULT_WEIGHTS
        if not path.exists():
            raise FileNotFoundError(
                f"no Pen expert weights at {path}; build them with examples/maintainer/train_pen_expert.py"
            )
        payload = safe_torch_load(path)
        policy = cls()
        policy.load_state_dict(payload["state_dict"])
        return policy.eval()

    def save(self, path: str | Path, metadata: dict | None = None) -> None:
        """Writes the weights (normalisation included) and optional metadata (plain values), atomically."""
        save_checkpoint(path, {"state_dict": self.state_dict(), "metadata": metadata or {}})
