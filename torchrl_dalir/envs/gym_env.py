"""Gymnasium-level environments: the simulator, seeded per episode, with point-cloud observations.

Everything simulator-specific stays below the TorchRL wrapper: MetaWorld's seeding quirks,
the success flag's type, the early termination at the first success, and the depth camera.
"""

from __future__ import annotations

import copy
import warnings
from dataclasses import dataclass

import gymnasium as gym
import mujoco
import numpy as np

from torchrl_dalir import keys
from torchrl_dalir.config import check_at_least
from torchrl_dalir.envs.point_cloud import DepthPointCloudCamera, RGBCamera
from torchrl_dalir.envs.tasks import METAWORLD, TaskSpec


class _MetaWorldSeeding(gym.Wrapper):
    """Makes ``reset(seed=s)`` reproducible for MetaWorld v3, whose ``reset`` ignores seeds.

    The env is fully randomised (object and goal positions drawn from its own generator at every
    reset, as DP3 does), rather than cycling through MT1's 50 fixed task variations.
    """

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.env.unwrapped.seed(int(seed))
        return self.env.reset(options=options)


class EpisodeSeeds(gym.Wrapper):
    """Resets episode ``i`` with seed ``first + i * stride`` and reports it as ``info["episode_seed"]`` (at the
    reset and every step), so that each episode depends on its seed only, not on what ran before it in the env.

    A reset that follows another one without a step in between starts no episode and takes no new seed (TorchRL
    may reset twice before the first step); an explicit ``reset(seed=s)`` restarts the schedule at ``s``.
    """

    def __init__(self, env: gym.Env, first: int, stride: int):
        super().__init__(env)
        self.next_seed, self.stride = first, stride
        self.seed_now: int | None = None

    @property
    def task(self) -> TaskSpec:  # what env_task reads through TorchRL's GymWrapper
        return self.env.task

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.next_seed = seed
        elif self.seed_now is not None and not self._stepped:
            self.next_seed = self.seed_now  # the last reset started no episode: take its seed again
        self.seed_now, self._stepped = self.next_seed, False
        self.next_seed += self.stride
        observation, info = self.env.reset(seed=self.seed_now, options=options)
        return observation, self._tagged(info)

    def step(self, action):
        self._stepped = True
        *out, info = self.env.step(action)
        return *out, self._tagged(info)

    def _tagged(self, info: dict) -> dict:
        return {**info, keys.EPISODE_SEED: np.array([self.seed_now], dtype=np.int64)}


def make_simulator(task: TaskSpec) -> gym.Env:
    """The raw gymnasium env of a task, with its step limit and the privileged state observation."""
    if task.suite == METAWORLD:
        import metaworld  # noqa: F401  (registers the MetaWorld envs)
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS

        raw = ALL_V3_ENVIRONMENTS[task.env_id]()
        raw._partially_observable = False  # the goal position is part of the privileged state
        raw.__dict__.pop("sawyer_observation_space", None)  # cached for the old observability
        raw._freeze_rand_vec = False
        raw.seeded_rand_vec = True
        raw._set_task_called = True
        env = gym.wrappers.TimeLimit(raw, max_episode_steps=task.max_steps)
        return _MetaWorldSeeding(env)
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    return gym.make(task.env_id, max_episode_steps=task.max_steps)


_PHYSICS_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # qpos, qvel, controls, mocap, warm start, ...
_STEP_BOOKKEEPING = ("curr_path_length", "_prev_obs", "_last_stable_obs")  # MetaWorld's per-step attributes


@dataclass
class SimulatorState:
    """What :meth:`PointCloudObservation.get_state` saves: MuJoCo's integration state, the
    simulator's own per-step attributes and the step limit's counter."""

    physics: np.ndarray
    attributes: dict
    elapsed_steps: int | None


def _time_limit(env: gym.Env) -> gym.wrappers.TimeLimit | None:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, gym.wrappers.TimeLimit):
            return env
        env = env.env
    return None


_WARNED_REPEATS: set[tuple[str, int]] = set()  # (task, num_points) already warned about in this process


def _warn_if_points_repeat(task: TaskSpec, num_points: int, available: int) -> None:
    """Warns, once per task and cloud size in a process, when the crop box holds fewer distinct
    points than a cloud has rows (farthest-point sampling then repeats points)."""
    if available >= num_points or (task.name, num_points) in _WARNED_REPEATS:
        return
    _WARNED_REPEATS.add((task.name, num_points))
    warnings.warn(
        f"{task.name}: the crop box holds {available} distinct points at the first observation, fewer than "
        f"num_points={num_points}, so each cloud repeats points to fill {num_points} rows. For distinct points only, "
        f"pass make_env(..., num_points={available}) or fewer (a max-pooled encoder sees the same set either way)",
        stacklevel=2,
    )


class PointCloudObservation(gym.Wrapper):
    """Replaces the observation by ``point_cloud``, ``agent_pos`` and ``privileged_state``.

    ``info["success"]`` becomes a bool and the episode terminates at the first success. The
    depth camera is created at the first reset, in the process that steps the env. With
    ``render=False`` there is no point cloud: a state-only env, ~10x faster, for experts. With
    ``pixels > 0``, ``pixels`` holds an RGB render ``[pixels, pixels, 3]`` from the same camera (for
    videos; none by default).

    With ``decision_period=k > 1`` a cloud is rendered only for the observations that a policy deciding
    at steps 0, k, 2k, ... reads (the last ``history`` up to each decision) and for the observation
    at which the env ends an episode (success or the step limit: its outcome, e.g. for a scorer);
    the others are NaN, including the last one of a rollout cut short by its own ``max_steps``.
    Rendering leaves the physics untouched, so the episode is the same, with about ``k / history``
    times fewer renders if ``k > history``. Steps are counted by the step limit, whose count :meth:`set_state` restores.
    """

    def __init__(
        self,
        env: gym.Env,
        task: TaskSpec,
        num_points: int = 512,
        render: bool = True,
        pixels: int = 0,
        decision_period: int = 1,
        history: int = 1,
    ):
        super().__init__(env)
        self.task = task
        self.num_points = num_points
        self.render_points = render
        self.pixels = pixels
        check_at_least("decision_period", decision_period, 1)
        check_at_least("history", history, 1)
        self.decision_period, self.history = decision_period, history
        self._limit = _time_limit(env)  # the step limit's wrapper, found once: it counts the episode's steps
        if decision_period > 1 and self._limit is None:
            raise ValueError(
                f"decision_period={decision_period} counts steps with the env's step limit, "
                f"and {task.name}'s env has none"
            )
        state_dim = len(task.privileged_state(env.unwrapped, env.observation_space.sample()))
        unbounded = dict(low=-np.inf, high=np.inf, dtype=np.float32)
        spaces = {
            keys.AGENT_POS: gym.spaces.Box(shape=(task.agent_pos_dim,), **unbounded),
            keys.PRIVILEGED_STATE: gym.spaces.Box(shape=(state_dim,), **unbounded),
        }
        if render:
            spaces[keys.POINT_CLOUD] = gym.spaces.Box(shape=(num_points, 3), **unbounded)
        if pixels:
            spaces[keys.PIXELS] = gym.spaces.Box(0, 255, shape=(pixels, pixels, 3), dtype=np.uint8)
        self.observation_space = gym.spaces.Dict(spaces)
        self._camera: DepthPointCloudCamera | None = None
        self._rgb_camera: RGBCamera | None = None

    def _observation(self, state: np.ndarray, last: bool = False) -> dict[str, np.ndarray]:
        raw = self.env.unwrapped
        observation = {
            keys.AGENT_POS: np.asarray(self.task.agent_pos(raw, state), dtype=np.float32),
            keys.PRIVILEGED_STATE: np.asarray(self.task.privileged_state(raw, state), dtype=np.float32),
        }
        if self.render_points and not (last or self._read_by_a_decision()):
            observation[keys.POINT_CLOUD] = np.full((self.num_points, 3), np.nan, dtype=np.float32)
        elif self.render_points:
            first = self._camera is None
            if first:
                t = self.task
                self._camera = DepthPointCloudCamera(
                    raw.model, t.camera, t.crop_low, t.crop_high, self.num_points, t.image_size
                )
            observation[keys.POINT_CLOUD] = self._camera(raw.data)
            if first:
                _warn_if_points_repeat(self.task, self.num_points, self._camera.points_in_crop)
        if self.pixels:
            if self._rgb_camera is None:
                self._rgb_camera = RGBCamera(raw.model, self.task.camera, self.pixels)
            observation[keys.PIXELS] = self._rgb_camera(raw.data)
        return observation

    def _read_by_a_decision(self) -> bool:
        """Whether a decision every ``decision_period`` steps reads the current observation (it
        reads the last ``history`` ones: steps ``t`` with ``(t + history - 1) mod period < history``)."""
        if self.decision_period == 1:
            return True
        step = self._limit._elapsed_steps  # 0 after a reset, t after the t-th step
        return (step + self.history - 1) % self.decision_period < self.history

    def reset(self, *, seed=None, options=None):
        state, _ = self.env.reset(seed=seed, options=options)
        return self._observation(state), {keys.SUCCESS: np.zeros(1, dtype=bool)}

    def step(self, action):
        if not np.isfinite(action).all():  # MuJoCo would reset the simulation and the episode would go on
            raise ValueError(
                f"the action {np.asarray(action).tolist()} holds NaN or infinite values: check what the policy outputs"
            )
        state, reward, terminated, truncated, info = self.env.step(action)
        success = bool(info.get("success", False))
        info = {keys.SUCCESS: np.array([success])}
        terminated = terminated or success
        return self._observation(state, last=terminated or truncated), float(reward), terminated, truncated, info

    def get_state(self) -> SimulatorState:
        """A snapshot of the episode, so that after :meth:`set_state` the same actions give the
        same observations (to try several action chunks from one state)."""
        raw = self.env.unwrapped
        physics = np.empty(mujoco.mj_stateSize(raw.model, _PHYSICS_STATE))
        mujoco.mj_getState(raw.model, raw.data, physics, _PHYSICS_STATE)
        attributes = {name: copy.deepcopy(getattr(raw, name)) for name in _STEP_BOOKKEEPING if hasattr(raw, name)}
        return SimulatorState(physics, attributes, self._limit._elapsed_steps if self._limit is not None else None)

    def set_state(self, state: SimulatorState) -> None:
        """Returns the episode to a :meth:`get_state` snapshot: the same actions then give the same
        episode, bit for bit, as from the moment the snapshot was taken."""
        raw = self.env.unwrapped
        mujoco.mj_setState(raw.model, raw.data, state.physics, _PHYSICS_STATE)
        mujoco.mj_forward(raw.model, raw.data)  # body, site and camera poses for the next observation
        # mj_forward also overwrote the solver's warm start, which the next step reads: restore it (without this,
        # an 80-step continuation drifted by up to 2e-4 in joint velocities from the un-restored episode)
        mujoco.mj_setState(raw.model, raw.data, state.physics, _PHYSICS_STATE)
        for name, value in state.attributes.items():
            setattr(raw, name, copy.deepcopy(value))
        if self._limit is not None:
            self._limit._elapsed_steps = state.elapsed_steps

    def close(self):
        for camera in (self._camera, self._rgb_camera):
            if camera is not None:
                camera.close()
        self._camera = self._rgb_camera = None
        super().close()
