"""MetaWorld's scripted experts (``metaworld.policies``) as a TorchRL policy module."""

from __future__ import annotations

import warnings

import numpy as np
import torch
from torch import nn


class MetaWorldScriptedPolicy(nn.Module):
    """Maps ``privileged_state`` ``[..., 39]`` to a 4-D action with MetaWorld's scripted policy.

    The scripted policies are stateless numpy functions of the full state (goal included); the
    module loops over the batch and clips actions to the action space, as the env would.
    """

    def __init__(self, env_id: str):
        super().__init__()
        from metaworld.policies import ENV_POLICY_MAP

        if env_id not in ENV_POLICY_MAP:
            raise KeyError(f"MetaWorld has no scripted policy for {env_id!r}")
        self.env_id = env_id
        self.policy = ENV_POLICY_MAP[env_id]()

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        flat = state.detach().reshape(-1, state.shape[-1]).cpu().double().numpy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "Constant(s) may be too high": the env clips anyway
            actions = np.stack([self.policy.get_action(s) for s in flat])
        actions = np.clip(actions, -1.0, 1.0).astype(np.float32)
        return torch.from_numpy(actions).reshape(*state.shape[:-1], -1).to(state.device)
