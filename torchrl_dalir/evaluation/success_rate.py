"""Success-rate evaluation on fixed, seeded evaluation episodes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import partial

import torch
from tensordict import TensorDictBase
from torchrl.envs import SerialEnv
from tqdm.auto import tqdm

from torchrl_dalir import keys
from torchrl_dalir.config import check_at_least
from torchrl_dalir.envs import get_task, make_env
from torchrl_dalir.seeds import check_eval_seed, eval_episode_seed


@dataclass
class EpisodeRecord:
    episode: int
    reset_seed: int
    success: bool
    steps: int  # steps taken; equals the steps to success when ``success``
    episode_return: float
    details: dict = field(default_factory=dict)  # ``describe(rollout)`` of ``evaluate``, e.g. DALI-R's choices


@dataclass
class EvaluationResult:
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
    """
    check_at_least("num_episodes", num_episodes, 1)
    check_eval_seed(seed)
    env = env if env is not None else SerialEnv(1, partial(make_env, task, seed=None, **env_kwargs))
    max_steps = get_task(task).max_steps
    records = []
    for episode in tqdm(range(num_episodes), desc=f"evaluate {task}", disable=not progress, leave=False):
        reset_seed = eval_episode_seed(seed, episode)
        td = env.reset(seed=reset_seed)
        rollout = env.rollout(max_steps, policy, auto_reset=False, tensordict=td, break_when_any_done=True)
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
    return EvaluationResult(task=task, episodes=records)
