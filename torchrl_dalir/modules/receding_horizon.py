"""Receding-horizon execution: run ``action_steps`` actions of each predicted chunk, then replan."""

from __future__ import annotations

from collections.abc import Sequence

from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.modules.tensordict_module.actors import MultiStepActorWrapper

from torchrl_dalir import keys
from torchrl_dalir.modules.config import executed_slice

ACTION_PLAN = "action_plan"  # [..., action_steps, A], the part of the chunk that will be executed


class ExecutedActions(TensorDictModuleBase):
    """Writes ``action_plan``: the ``action_steps`` chunk entries from the current step on.

    A chunk starts at the oldest observation step, so the current step is index ``obs_steps - 1``.
    """

    in_keys = [keys.ACTION_CHUNK]
    out_keys = [ACTION_PLAN]

    def __init__(self, obs_steps: int, action_steps: int):
        super().__init__()
        self.executed = executed_slice(obs_steps, action_steps)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        chunk = tensordict.get(keys.ACTION_CHUNK)
        return tensordict.set(ACTION_PLAN, chunk[..., self.executed, :])


class RepeatPerStep(TensorDictModuleBase):
    """Writes ``("plan", *key)``: each ``key`` repeated over ``action_steps``, so that values
    computed once per decision (e.g. DALI-R's candidate scores) travel with the executed actions."""

    def __init__(self, decision_keys: Sequence[NestedKey], action_steps: int):
        super().__init__()
        self.in_keys = list(decision_keys)
        self.out_keys = [plan_key(key) for key in decision_keys]
        self.action_steps = action_steps

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        for key, out in zip(self.in_keys, self.out_keys):
            value = tensordict.get(key)
            at = tensordict.ndim
            tensordict.set(out, value.unsqueeze(at).expand(*value.shape[:at], self.action_steps, *value.shape[at:]))
        return tensordict


def plan_key(key: NestedKey) -> tuple[str, ...]:
    return ("plan", *((key,) if isinstance(key, str) else key))


def receding_horizon(
    chunk_policy: TensorDictModuleBase, obs_steps: int, action_steps: int, decision_keys: Sequence[NestedKey] = ()
) -> MultiStepActorWrapper:
    """Wraps any module that writes ``action_chunk`` into a TorchRL actor that executes
    ``action_steps`` actions per decision (TorchRL's ``MultiStepActorWrapper``), so
    ``env.rollout(policy=...)`` and collectors run it unchanged. The env needs ``is_init``
    (``make_env`` adds an ``InitTracker``).

    ``decision_keys``: other outputs of ``chunk_policy`` to keep; every step then carries the
    value of the decision its action came from (the wrapper keeps only chunked keys otherwise).
    """
    decision_keys = list(decision_keys)
    modules = [chunk_policy, ExecutedActions(obs_steps, action_steps)]
    if decision_keys:
        modules.append(RepeatPerStep(decision_keys, action_steps))
    return MultiStepActorWrapper(
        TensorDictSequential(*modules),
        n_steps=action_steps,
        action_keys=[keys.ACTION, *decision_keys],
        chunk_keys=[ACTION_PLAN, *(plan_key(key) for key in decision_keys)],
    )
