"""Observation history: the one rule for which observations make a step's ``To``-step history.

The history of step ``t`` holds the observations of steps ``t - To + 1 .. t``, oldest first;
before the episode start the first observation repeats (DP3's padding). The env stacks it as it
steps (:func:`append_history`, TorchRL's ``CatFrames``), the training windows gather it from stored
episodes (:class:`~torchrl_dalir.data.windows.TrajectoryWindows`) and the reranking diagnostics from
the observations of the running episode (:func:`latest_history`), all by :func:`history_steps`;
``tests/test_windows.py`` checks that the three agree on the same episode.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey
from torchrl.envs import CatFrames, TransformedEnv, UnsqueezeTransform


def history_steps(step: int | torch.Tensor, length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The steps whose observations make the ``length``-step history of ``step`` (``[..., length]``,
    oldest first, step 0 repeating before the episode start) and which of them are such padding.

    Example:
        >>> steps, is_pad = history_steps(torch.tensor([0, 1, 5]), 3)
        >>> steps
        tensor([[0, 0, 0],
                [0, 0, 1],
                [3, 4, 5]])
        >>> is_pad[1].tolist()
        [True, False, False]
    """
    wanted = torch.as_tensor(step)[..., None] + torch.arange(1 - length, 1)
    return wanted.clamp(min=0), wanted < 0


def latest_history(observations: Sequence, length: int) -> list:
    """The ``length``-step history of the latest of an episode's ``observations`` (all of them so far).

    Example:
        >>> latest_history(["s0"], 2), latest_history(["s0", "s1", "s2"], 2)
        (['s0', 's0'], ['s1', 's2'])
    """
    steps, _ = history_steps(len(observations) - 1, length)
    return [observations[i] for i in steps.tolist()]


def append_history(env: TransformedEnv, length: int, entries: Sequence[tuple[NestedKey, int]]) -> TransformedEnv:
    """Makes each of ``env``'s ``entries`` (key, new history dimension) carry its ``length``-step history,
    stacked by TorchRL's ``CatFrames`` as the env steps (reset at every episode start, where the first
    observation repeats: ``padding="same"``)."""
    for key, dim in entries:
        env.append_transform(UnsqueezeTransform(dim=dim, in_keys=[key]))
        env.append_transform(CatFrames(N=length, dim=dim, in_keys=[key], padding="same"))
    return env
