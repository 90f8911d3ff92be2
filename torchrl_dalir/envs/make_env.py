"""``make_env``: a benchmark task as a TorchRL environment with point-cloud observations."""

from __future__ import annotations

from functools import cache

import torch
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, GymWrapper, InitTracker, ParallelEnv, StepCounter, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase
from torchrl.envs.gym_like import default_info_dict_reader

from torchrl_dalir import keys
from torchrl_dalir.config import check_at_least
from torchrl_dalir.envs.gym_env import EpisodeSeeds, PointCloudObservation, make_simulator
from torchrl_dalir.envs.history import append_history
from torchrl_dalir.envs.tasks import TaskSpec, get_task


def make_env(
    task: str | TaskSpec,
    *,
    seed: int | None = 0,
    seed_stride: int = 0,
    num_points: int = 512,
    render: bool = True,
    history: int = 1,
    pixels: int = 0,
    decision_period: int = 1,
    step_counter: bool = False,
    device: str | torch.device = "cpu",
) -> EnvBase:
    """Builds a TorchRL env for a benchmark task (``door``, ``pen``, ``disassemble``, ...).

    Observations: ``point_cloud`` ``[num_points, 3]``, ``agent_pos`` and ``privileged_state``
    (for experts only). ``("next", "success")`` is the simulator's success flag; the reward is
    the env's dense reward. An episode terminates at its first success and is truncated at the
    task's step limit. An ``InitTracker`` marks episode starts (``is_init``).

    Args:
        task: a name from :data:`torchrl_dalir.envs.TASKS`, any MetaWorld v3 task name, or a
            :class:`TaskSpec`.
        seed: seeds the first episode; the same seed gives the same episodes. ``None`` leaves
            the env unseeded. In a ``SerialEnv``/``ParallelEnv``, ``reset(seed=s)`` gives every
            worker the same seed, hence the same episode (TorchRL passes reset keywords to each
            worker); seed the workers apart with ``env.set_seed(s)`` or
            ``env.reset(list_of_kwargs=[{"seed": s + i} for i in range(env.num_workers)])``.
        seed_stride: with ``k > 0``, episode ``i`` resets with ``seed + i * k`` (an episode then depends on its
            seed only, not on the episodes before it) and the observations carry that seed as ``episode_seed``;
            a collection's worker ``w`` of ``k`` runs episodes ``seed + w``, ``seed + w + k``, ... this way.
            ``0`` (the default): later episodes follow from the simulator's own generator.
        num_points: points per cloud after farthest-point sampling. If the task's crop box holds
            fewer pixels of the depth image than that, points repeat (a warning at the first
            observation says how many are distinct).
        render: ``False`` gives a state-only env without ``point_cloud`` (for experts; ~10x faster).
        history: with ``history > 1``, ``point_cloud`` and ``agent_pos`` carry the last
            ``history`` observations (``[history, N, 3]``, ``[history, D]``), stacked by TorchRL's
            ``CatFrames`` (the first observation repeats at an episode start, as DP3 pads; the rule of
            :mod:`torchrl_dalir.envs.history`, shared with the training windows).
        pixels: with ``pixels > 0``, ``pixels`` holds an RGB render ``[pixels, pixels, 3]`` (uint8)
            from the task's camera at every step, for videos (TorchRL's ``VideoRecorder`` reads it;
            see :mod:`torchrl_dalir.evaluation.video`). ``0`` (the default) renders none.
        decision_period: with ``k > 1``, point clouds are rendered only for the observations that a
            policy deciding every ``k`` steps reads (a receding-horizon actor executing ``k`` actions
            per chunk: the last ``history`` observations up to each decision) and are NaN at the other
            steps; the episodes are the same, with about ``k / history`` times fewer renders (if ``k > history``). For
            evaluation, where nothing else reads the clouds (:func:`~torchrl_dalir.evaluation.evaluate`
            sets it); the policies and DALI-R's actor refuse a NaN cloud, so a decision at another step fails loudly.
        step_counter: add TorchRL's ``StepCounter``: ``step_count``, the steps since the episode's start (what
            ``RerankingConfig(decisions=n)`` counts decisions by, for ``n > 1``).
        device: where the env's tensors live.

    Example:
        >>> from torchrl_dalir import make_env
        >>> env = make_env("disassemble", seed=0)  # doctest: +SKIP
        >>> rollout = env.rollout(5)  # doctest: +SKIP
        >>> rollout["point_cloud"].shape  # doctest: +SKIP
        torch.Size([5, 512, 3])
    """
    check_at_least("num_points", num_points, 1)
    check_at_least("history", history, 1)
    check_at_least("pixels", pixels, 0)
    check_at_least("seed_stride", seed_stride, 0)
    check_at_least("decision_period", decision_period, 1)
    if seed_stride and seed is None:
        raise ValueError("seed_stride needs a seed: the first episode's")
    spec = get_task(task)
    simulator = PointCloudObservation(make_simulator(spec), spec, num_points, render, pixels, decision_period, history)
    info_spec = Composite({keys.SUCCESS: Categorical(2, shape=(1,), dtype=torch.bool, device=device)})
    if seed_stride:
        simulator = EpisodeSeeds(simulator, seed, seed_stride)
        info_spec[keys.EPISODE_SEED] = Unbounded(shape=(1,), dtype=torch.int64, device=device)
    env = GymWrapper(simulator, device=device)
    env.set_info_dict_reader(default_info_dict_reader(list(info_spec.keys()), spec=info_spec))
    env = TransformedEnv(env, InitTracker())
    if step_counter:
        env.append_transform(StepCounter())
    if history > 1:
        append_history(env, history, [(keys.AGENT_POS, -2)] + ([(keys.POINT_CLOUD, -3)] if render else []))
    if seed is not None and not seed_stride:
        env.set_seed(seed)
    return env


def action_bounds(task: str | TaskSpec) -> tuple[torch.Tensor, torch.Tensor]:
    """The bounds ``low``, ``high`` ``[A]`` that ``task``'s simulator clips every action to (its action
    space, the env's ``action_spec``): an action beyond them is executed clipped."""
    low, high = _action_space_bounds(get_task(task))
    return low.clone(), high.clone()


@cache
def _action_space_bounds(task: TaskSpec) -> tuple[torch.Tensor, torch.Tensor]:
    simulator = make_simulator(task)  # once per process and task
    try:
        space = simulator.action_space
        return torch.as_tensor(space.low, dtype=torch.float32), torch.as_tensor(space.high, dtype=torch.float32)
    finally:
        simulator.close()


def env_task(env: EnvBase) -> str | None:
    """The name of the task an env built by :func:`make_env` runs, also as the workers of a
    ``SerialEnv`` or ``ParallelEnv`` (started if needed; they must all run the same task);
    ``None`` for any other env."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    if not isinstance(env, BatchedEnvBase):
        found = [getattr(env, "task", None)]  # a GymWrapper forwards to PointCloudObservation.task
    else:
        if isinstance(env, ParallelEnv) and not _workers_run_point_clouds(env):
            return None  # asking a worker for an attribute it lacks kills it
        if env.is_closed:
            env.start()
        try:
            found = list(env.task)
        except AttributeError:
            return None
    if not found or not all(isinstance(task, TaskSpec) for task in found):
        return None
    names = sorted({task.name for task in found})
    if len(names) > 1:
        raise ValueError(f"the env's workers run different tasks: {names}")
    return names[0]


def _workers_run_point_clouds(env: ParallelEnv) -> bool:
    """Whether the metadata of every worker shows an env of :func:`make_env`."""
    meta = getattr(env, "meta_data", None)
    meta = meta if isinstance(meta, list) else [meta]
    return all(PointCloudObservation.__name__ in getattr(m, "env_str", "") for m in meta)
