"""Receding-horizon execution: run ``action_steps`` actions of each predicted chunk, then replan."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.envs import EnvBase
from torchrl.modules.tensordict_module.actors import MultiStepActorWrapper

from torchrl_dalir import keys
from torchrl_dalir.envs.make_env import env_task
from torchrl_dalir.modules.config import executed_slice
from torchrl_dalir.modules.policy_interface import ChunkPolicy, read_observation

ACTION_PLAN = "action_plan"  # [..., action_steps, A], the part of the chunk that will be executed


class ExecutedActions(TensorDictModuleBase):
    """Writes ``action_plan``: the ``action_steps`` chunk entries from the current step on.

    A chunk starts at the oldest observation step, so the current step is index ``obs_steps - 1``.
    """

    def __init__(self, obs_steps: int, action_steps: int, chunk_key: NestedKey = keys.ACTION_CHUNK):
        super().__init__()
        self.in_keys, self.out_keys = [chunk_key], [ACTION_PLAN]
        self.executed = executed_slice(obs_steps, action_steps)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        chunk = tensordict.get(self.in_keys[0])
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


def base_policy(actor: TensorDictModuleBase) -> ChunkPolicy | None:
    """The chunk policy an actor samples from: the actor itself, or its ``policy`` (DALI-R, the dropout policy),
    if it is a :class:`~torchrl_dalir.modules.ChunkPolicy` (which states its chunk sizes)."""
    for module in (actor, getattr(actor, "policy", None)):
        if module is not None and isinstance(module, ChunkPolicy):
            return module
    return None


class RecedingHorizonActor(MultiStepActorWrapper):
    """TorchRL's ``MultiStepActorWrapper`` made to run unchanged on an un-batched env, in
    ``SerialEnv`` and ``ParallelEnv`` and in collectors over each. Build it with
    :func:`~torchrl_dalir.receding_horizon`.

    Each batch entry replans at its own episode start (``is_init``) or when its plan is used up;
    the others go on with theirs. As in TorchRL, the plan and the step counter travel with the
    tensordict, but ``ParallelEnv`` drops them between steps (only the env's own entries pass
    between processes): the actor then goes on from its own copy of the plans it last wrote (one
    row per env, as :class:`~torchrl_dalir.experts.drift_noise.DriftNoise` keeps its noise), so
    an actor object serves one ``ParallelEnv`` at a time. An un-batched env acts as a batch of one.
    """

    def __init__(
        self,
        actor: TensorDictModuleBase,
        obs_steps: int,
        action_steps: int,
        decision_keys: Sequence[NestedKey],
        chunk_key: NestedKey,
        action_key: NestedKey,
        init_key: NestedKey,
    ):
        decision_keys = list(decision_keys)
        modules = [actor, ExecutedActions(obs_steps, action_steps, chunk_key)]
        if decision_keys:
            modules.append(RepeatPerStep(decision_keys, action_steps))
        super().__init__(
            TensorDictSequential(*modules),
            n_steps=action_steps,
            action_keys=[action_key, *decision_keys],
            chunk_keys=[ACTION_PLAN, *(plan_key(key) for key in decision_keys)],
            init_key=init_key,
        )
        self.obs_steps, self.action_steps, self.decision_keys = obs_steps, action_steps, decision_keys
        self._plan: TensorDictBase | None = None  # [*batch] the chunk keys of every entry's current plan
        self._counter: torch.Tensor | None = None  # [*batch] actions taken from it

    @property
    def chunk_actor(self) -> TensorDictModuleBase:
        """The wrapped actor (that writes whole chunks)."""
        return self.actor[0]

    def reset(self, seed: int | None = None) -> None:
        """Forgets every plan and restarts the wrapped actor's own random stream (its ``reset``,
        e.g. :meth:`RerankingActor.reset <torchrl_dalir.reranking.RerankingActor.reset>`), so the
        same object replays its episodes. A base policy draws from torch's global generator until
        it is given a seed here (:meth:`ChunkPolicy3D.reset <torchrl_dalir.modules.ChunkPolicy3D.reset>`)."""
        self._plan = self._counter = None
        restart = getattr(self.chunk_actor, "reset", None)
        if restart is not None:
            restart(seed)
        elif seed is not None:
            raise ValueError(
                f"{type(self.chunk_actor).__name__} has no random stream of its own to seed: use torch.manual_seed"
            )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_dims == 0:  # an un-batched env: act as a batch of one
            out = super().forward(tensordict.unsqueeze(0)).squeeze(0)
            return tensordict.update(out.select(*self.out_keys, strict=False))
        return super().forward(tensordict)

    def _init(self, tensordict: TensorDictBase) -> None:
        is_init = tensordict.get(self.init_key, default=None)
        if is_init is None:
            raise KeyError(f"the receding-horizon actor needs {self.init_key!r} (an InitTracker; make_env adds one)")
        replan = is_init.reshape(tensordict.shape)
        try:  # TorchRL's way: the tensordict carries the plan and the counter
            carried = tensordict.select(*self.chunk_keys, self.counter_key)
            self._plan, self._counter = (
                carried.exclude(self.counter_key),
                carried.get(self.counter_key).reshape(tensordict.shape),
            )
        except KeyError:  # dropped (ParallelEnv) or not there yet: the plans last written stand in
            pass
        if self._plan is None or self._plan.batch_size != tensordict.shape:
            if not replan.all():
                raise RuntimeError(
                    f"the receding-horizon actor holds no plan for a batch of {list(tensordict.shape)}: start every "
                    f"episode with env.reset() (which sets {self.init_key!r})"
                )
        else:
            replan = replan | (self._counter >= self.n_steps)
        if replan.all():
            self._plan = self.actor(tensordict.copy()).select(*self.chunk_keys)
            self._counter = torch.zeros(tensordict.shape, dtype=torch.int32, device=is_init.device)
        elif replan.any():  # out of place: earlier steps of a rollout hold the old plan
            plan = self._plan.clone()
            plan[replan] = self.actor(tensordict[replan]).select(*self.chunk_keys)
            self._plan, self._counter = plan, self._counter.masked_fill(replan, 0)
        self._counter = self._counter + 1
        tensordict.update(self._plan)
        tensordict.set(self.counter_key, self._counter.reshape(is_init.shape))


def check_env(actor: TensorDictModuleBase, env: EnvBase, action_key: NestedKey = keys.ACTION) -> None:
    """Refuses an env that ``actor``'s policy was not trained for: another task, observation
    history, cloud size, robot state or action size."""
    policy = base_policy(actor)
    if policy is None:
        return
    read_observation(policy, env.fake_tensordict(), actor.in_keys[:2])  # history, cloud and state sizes
    action_dim = env.full_action_spec[action_key].shape[-1]
    if action_dim != policy.action_dim:
        raise ValueError(f"the env takes {action_dim}-D actions; the policy outputs {policy.action_dim}-D")
    task, trained_on = env_task(env), getattr(policy, "task", None)
    if trained_on is not None and task is not None and task != trained_on.removesuffix("-v3"):
        raise ValueError(f"the policy was trained on task {trained_on!r}; the env runs {task!r}")


def receding_horizon(
    chunk_policy: TensorDictModuleBase,
    obs_steps: int | None = None,
    action_steps: int | None = None,
    decision_keys: Sequence[NestedKey] | None = None,
    *,
    env: EnvBase | None = None,
    chunk_key: NestedKey = keys.ACTION_CHUNK,
    action_key: NestedKey = keys.ACTION,
    init_key: NestedKey = keys.IS_INIT,
) -> RecedingHorizonActor:
    """Wraps any module that writes ``action_chunk`` into a TorchRL actor that executes
    ``action_steps`` actions per decision (:class:`~torchrl_dalir.modules.receding_horizon.RecedingHorizonActor`), so
    ``env.rollout(policy=...)`` and collectors run it unchanged, on an un-batched or a batched
    env. The env needs ``is_init`` (``make_env`` adds an ``InitTracker``).

    ``obs_steps`` and ``action_steps`` default to those of the policy that ``chunk_policy`` is or
    wraps (a base policy or any :class:`~torchrl_dalir.modules.ChunkPolicy`,
    :class:`~torchrl_dalir.reranking.RerankingActor`); other values are refused. ``decision_keys``:
    other outputs of ``chunk_policy`` to keep (default: all of its ``out_keys`` but ``chunk_key``,
    e.g. DALI-R's candidate scores and choice); every step then
    carries the value of the decision its action came from. With ``env``, an env that the policy
    was not trained for (another task, history, cloud size or state size) is refused here;
    without it, a wrong observation is refused at the first decision.
    """
    policy = base_policy(chunk_policy)
    if policy is None:
        if obs_steps is None or action_steps is None:
            raise ValueError(f"{type(chunk_policy).__name__} carries no policy config: pass obs_steps and action_steps")
    else:
        given = {"obs_steps": obs_steps, "action_steps": action_steps}
        for name, value in given.items():
            if value is not None and value != getattr(policy, name):
                raise ValueError(
                    f"{name}={value}, but the policy was trained with {name}={getattr(policy, name)} "
                    "(leave it out: the policy's own is used)"
                )
        obs_steps, action_steps = policy.obs_steps, policy.action_steps
    if decision_keys is None:
        decision_keys = [key for key in chunk_policy.out_keys if key != unravel_key(chunk_key)]
    if env is not None:
        check_env(chunk_policy, env, action_key)
    return RecedingHorizonActor(chunk_policy, obs_steps, action_steps, decision_keys, chunk_key, action_key, init_key)
