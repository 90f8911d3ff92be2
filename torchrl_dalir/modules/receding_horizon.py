"""Receding-horizon execution: run ``action_steps`` actions of each predicted chunk, then replan."""

from __future__ import annotations

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.modules.tensordict_module.actors import MultiStepActorWrapper

from torchrl_dalir import keys

ACTION_PLAN = "action_plan"  # [..., action_steps, A], the part of the chunk that will be executed


class ExecutedActions(TensorDictModuleBase):
    """Writes ``action_plan``: the ``action_steps`` chunk entries from the current step on.

    A chunk starts at the oldest observation step, so the current step is index ``obs_steps - 1``.
    """

    in_keys = [keys.ACTION_CHUNK]
    out_keys = [ACTION_PLAN]

    def __init__(self, obs_steps: int, action_steps: int):
        super().__init__()
        self.start, self.stop = obs_steps - 1, obs_steps - 1 + action_steps

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        chunk = tensordict.get(keys.ACTION_CHUNK)
        return tensordict.set(ACTION_PLAN, chunk[..., self.start : self.stop, :])


def receding_horizon(chunk_policy: TensorDictModuleBase, obs_steps: int, action_steps: int) -> MultiStepActorWrapper:
    """Wraps any module that writes ``action_chunk`` into a TorchRL actor that executes
    ``action_steps`` actions per decision (TorchRL's ``MultiStepActorWrapper``), so
    ``env.rollout(policy=...)`` and collectors run it unchanged. The env needs ``is_init``
    (``make_env`` adds an ``InitTracker``)."""
    planner = TensorDictSequential(chunk_policy, ExecutedActions(obs_steps, action_steps))
    return MultiStepActorWrapper(planner, n_steps=action_steps, action_keys=[keys.ACTION], chunk_keys=[ACTION_PLAN])
