"""Success-rate evaluation on fixed, seeded evaluation episodes."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.envs import SerialEnv, TransformedEnv
from tqdm.auto import tqdm

from torchrl_dalir import keys
from torchrl_dalir.config import check_at_least
from torchrl_dalir.envs import get_task, make_env
from torchrl_dalir.evaluation.video import VIDEO_SIZE, gif_recorder
from torchrl_dalir.modules.receding_horizon import RecedingHorizonActor
from torchrl_dalir.seeds import check_eval_seed, eval_episode_seed


@dataclass
class EpisodeRecord:
    """One evaluation episode: its index, reset seed, outcome, length and return.

    Example:
        >>> record = EpisodeRecord(episode=0, reset_seed=eval_episode_seed(0, 0), success=True, steps=42,
        ...                        episode_return=3.5)
        >>> record.reset_seed  # episode 0 under evaluation seed 0: the same episode for every policy
        1000000000
    """

    episode: int
    reset_seed: int
    success: bool
    steps: int  # steps taken; equals the steps to success when ``success``
    episode_return: float
    details: dict = field(default_factory=dict)  # ``describe(rollout)`` of ``evaluate``, e.g. DALI-R's choices


@dataclass
class EvaluationResult:
    """What :func:`evaluate` returns: the task and one :class:`EpisodeRecord` per episode.

    Example:
        >>> result = EvaluationResult("reach", [EpisodeRecord(0, 1000000000, True, 42, 3.5),
        ...                                     EpisodeRecord(1, 1000000001, False, 200, 0.7)])
        >>> result.success_rate, result.to_dict()["episodes"][1]["steps"]
        (0.5, 200)
    """

    task: str
    episodes: list[EpisodeRecord]

    @property
    def success_rate(self) -> float:
        return sum(e.success for e in self.episodes) / max(len(self.episodes), 1)

    def to_dict(self) -> dict:
        return {"task": self.task, "success_rate": self.success_rate, "episodes": [asdict(e) for e in self.episodes]}


@torch.no_grad()
def evaluate(
    policy,
    task: str,
    num_episodes: int,
    seed: int = 0,
    *,
    env=None,
    progress: bool = True,
    describe: Callable[[TensorDictBase], dict] | None = None,
    max_steps: int | None = None,
    video: int = 0,
    video_prefix: str | Path | None = None,
    episode_indices: Sequence[int] | None = None,
    stop_when: Callable[[list[EpisodeRecord]], bool] | None = None,
    **env_kwargs,
) -> EvaluationResult:
    """Runs ``policy`` for ``num_episodes`` evaluation episodes and records each one.

    Episode ``i`` resets with :func:`torchrl_dalir.seeds.eval_episode_seed` ``(seed, i)``, so two
    policies evaluated with the same ``seed`` meet the same episodes, and none of them is a
    data-generation episode. An episode succeeds if the success flag is set at any step.

    Args:
        policy: any TorchRL policy (a callable on a tensordict that writes ``action``).
        task: the task name.
        num_episodes: how many episodes.
        seed: the evaluation seed.
        env: an env of one episode at a time to reuse (by default ``SerialEnv(1, make_env(task, **env_kwargs))``).
        progress: show a progress bar.
        describe: computes extra per-episode values from the episode's rollout, kept in the
            record's ``details`` (e.g. :func:`torchrl_dalir.evaluation.compare.decision_summary`).
        max_steps: stops every episode after this many steps (default: the task's step limit), for
            quick checks.
        video: records the first ``video`` episodes (none by default) with TorchRL's
            ``VideoRecorder`` in an env of their own that also renders ``pixels``
            (:data:`~torchrl_dalir.evaluation.video.VIDEO_SIZE`), as ``<video_prefix>_<episode>.gif``
            (one frame at the reset and one per step). The episodes are the same as without.
        video_prefix: where the videos go: a folder and a file-name prefix, e.g. ``videos/base``.
        episode_indices: runs these episodes of ``seed`` (indices, in this order) instead of the
            first ``num_episodes``: the same initial states, though not the same policy noise, as
            in a run of all of them (the policy's random stream continues from one episode to the next).
        stop_when: called with the records so far after every episode; ``True`` ends the
            evaluation there (e.g. once the policy has failed often enough).

    For a :class:`~torchrl_dalir.modules.receding_horizon.RecedingHorizonActor` the envs built here render point
    clouds only for the observations its decisions read (``make_env``'s ``decision_period``, set to the
    actor's ``action_steps``): the same episodes with about ``action_steps / history`` times fewer
    renders. ``decision_period=1`` renders every step.
    """
    check_at_least("num_episodes", num_episodes, 1)
    check_eval_seed(seed)
    check_at_least("video", video, 0)
    if max_steps is not None:
        check_at_least("max_steps", max_steps, 1)
    if video and video_prefix is None:
        raise ValueError(f"video={video} needs video_prefix=<folder>/<name> for the files")
    if video and env is not None:
        raise ValueError("video= records in an env of its own (which renders pixels): pass env= or video=, not both")
    if isinstance(policy, RecedingHorizonActor):
        env_kwargs.setdefault("decision_period", policy.n_steps)  # nothing else reads the other clouds
    make = partial(make_env, task, seed=None, **env_kwargs)
    recording = None  # the env of the recorded episodes (the others render no pixels)
    if video:
        recorder = gif_recorder(Path(video_prefix).parent, Path(video_prefix).name)
        recording = TransformedEnv(SerialEnv(1, partial(make, pixels=VIDEO_SIZE)), recorder)
    max_steps = max_steps if max_steps is not None else get_task(task).max_steps
    indices = list(episode_indices) if episode_indices is not None else range(num_episodes)
    records = []
    for position, episode in enumerate(tqdm(indices, desc=f"evaluate {task}", disable=not progress, leave=False)):
        reset_seed = eval_episode_seed(seed, episode)
        if position < video:
            episode_env = recording
        else:
            env = env if env is not None else SerialEnv(1, make)
            episode_env = env
        td = episode_env.reset(seed=reset_seed)
        rollout = episode_env.rollout(max_steps, policy, auto_reset=False, tensordict=td, break_when_any_done=True)
        if episode_env is recording:
            recorder.dump(step=episode)
        success = bool(rollout["next", keys.SUCCESS].any())
        records.append(
            EpisodeRecord(
                episode=episode,
                reset_seed=reset_seed,
                success=success,
                steps=rollout.shape[-1],
                episode_return=float(rollout["next", keys.REWARD].sum()),
                details=describe(rollout) if describe is not None else {},
            )
        )
        if stop_when is not None and stop_when(records):
            break
    if recording is not None:
        recording.close()
    return EvaluationResult(task=task, episodes=records)
