"""Branching candidates in the simulator: each chunk executed from one saved state, then the base policy.

Common random numbers make branches comparable and cheap: the base policy's sampling noise at
decision ``j`` of an episode depends only on the episode and ``j`` (:func:`decision_noise`), and
candidate 0 is the base policy's own chunk, so the clean candidate's branch from decision ``j`` is
the base episode itself from there on. Used by the candidates' ceiling
(:mod:`~torchrl_dalir.branching.ceiling`) and the branched outcomes
(:mod:`~torchrl_dalir.branching.outcomes`).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import torch

from torchrl_dalir import keys
from torchrl_dalir.envs.gym_env import PointCloudObservation
from torchrl_dalir.envs.history import latest_history
from torchrl_dalir.modules.config import executed_slice


def stack_observations(observations: list[dict], device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    cloud = torch.as_tensor(np.stack([o[keys.POINT_CLOUD] for o in observations]), device=device)
    agent_pos = torch.as_tensor(np.stack([o[keys.AGENT_POS] for o in observations]), device=device)
    return cloud, agent_pos


def execute_actions(env: PointCloudObservation, actions: np.ndarray) -> tuple[list[dict], bool, bool]:
    """Steps ``actions`` until the episode ends; the observations, success, and whether it ended."""
    observations, success, ended = [], False, False
    for action in actions:
        observation, _, terminated, truncated, info = env.step(action)
        observations.append(observation)
        success, ended = bool(info[keys.SUCCESS][0]), terminated or truncated
        if ended:
            break
    return observations, success, ended


def observation_history(policy, observations: list[dict], device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The policy's input ``[1, To, ...]``: the history of the latest of an episode's ``observations``."""
    return tuple(x[None] for x in stack_observations(latest_history(observations, policy.obs_steps), device))


def _stream(*parts: int | str) -> torch.Generator:
    """A generator seeded by ``parts`` alone (a CRC of their text: stable across processes, unlike ``hash``)."""
    return torch.Generator().manual_seed(zlib.crc32(repr(parts).encode()))


def decision_noise(policy, episode_seed: int, decision: int) -> torch.Tensor:
    """The base policy's sampling noise ``[1, H, A]`` at ``decision`` of the episode reset with
    ``episode_seed``: the same for every branch that reaches that decision (common random numbers)."""
    shape = (1, policy.horizon, policy.action_dim)
    return torch.randn(shape, generator=_stream("base", episode_seed, decision))


@torch.no_grad()
def base_actions(policy, observations: list[dict], episode_seed: int, decision: int, device) -> np.ndarray:
    """The executed actions of the base policy's chunk at ``decision``, after the episode's ``observations``."""
    cloud, agent_pos = observation_history(policy, observations, device)
    noise = decision_noise(policy, episode_seed, decision).to(device)
    return executed_actions(policy, policy.sample(policy.encode(cloud, agent_pos), noise=noise)[0])


def base_decisions(env: PointCloudObservation, policy, reset_seed: int, decisions: int, device) -> Iterator[list[dict]]:
    """The observations up to each of the first ``decisions`` decisions of the base episode reset with
    ``reset_seed`` (the base policy's own chunks between them); ``env`` is at that decision's state when each is
    yielded. Fewer when the episode ends sooner."""
    observation, _ = env.reset(seed=reset_seed)
    observations = [observation]
    for decision in range(decisions):
        if decision:  # the base policy's chunk of the decision before
            new, _, ended = execute_actions(env, base_actions(policy, observations, reset_seed, decision - 1, device))
            if ended:
                return
            observations = observations + new
        yield observations


def continue_base(
    env: PointCloudObservation,
    policy,
    observations: list[dict],
    episode_seed: int,
    decision: int,
    device,
    visit: Callable | None = None,
) -> tuple[bool, int]:
    """Runs the base policy from ``decision`` to the episode's end; its success and the steps it took.
    ``visit(decision, observations)`` is called before each decision (the base episode records its states this way)."""
    steps = 0
    while True:
        if visit is not None:
            visit(decision, observations)
        new, success, ended = execute_actions(env, base_actions(policy, observations, episode_seed, decision, device))
        steps += len(new)
        if ended:
            return success, steps
        observations = observations + new
        decision += 1


@torch.no_grad()
def candidate_chunks(
    policy,
    generator,
    observations: list[dict],
    num_candidates: int,
    episode_seed: int,
    decision: int,
    name: str,
    device,
) -> torch.Tensor:
    """A decision's candidate chunks ``[K, H, A]``; candidate 0 is the base policy's own chunk, the others
    come from ``generator`` with fresh noise, all seeded by the episode, the decision and ``name``."""
    cloud, agent_pos = observation_history(policy, observations, device)
    stream = _stream(name, episode_seed, decision)
    clean = policy.sample(
        policy.encode(cloud, agent_pos), noise=decision_noise(policy, episode_seed, decision).to(device)
    )
    conditions = generator.conditions(policy, cloud, agent_pos, num_candidates, stream)[:, 1:]
    return torch.cat([clean, policy.sample(conditions, stream)[0]])


def executed_actions(policy, chunks: torch.Tensor) -> np.ndarray:
    """The actions ``[..., k, A]`` that the env executes of chunks ``[..., H, A]``."""
    return chunks[..., executed_slice(policy.obs_steps, policy.action_steps), :].cpu().numpy()


def branch(
    env: PointCloudObservation,
    policy,
    state,
    observations: list[dict],
    actions: np.ndarray,
    episode_seed: int,
    decision: int,
    device,
) -> tuple[bool, int]:
    """From simulator ``state`` (decision ``decision``), executes ``actions`` and continues with the base
    policy: whether the branch succeeded and how many steps after the decision it ended."""
    env.set_state(state)
    new, success, ended = execute_actions(env, actions)
    if ended:
        return success, len(new)
    success, steps = continue_base(env, policy, observations + new, episode_seed, decision + 1, device)
    return success, len(new) + steps


@dataclass
class BaseEpisode:
    """The base policy's episode from a reset: its outcome, and the simulator state and the observations so
    far at every decision (where candidates branch)."""

    reset_seed: int
    success: bool
    steps: int
    decisions: list[tuple]


def base_episode(env: PointCloudObservation, policy, reset_seed: int, device) -> BaseEpisode:
    """Resets ``env`` with ``reset_seed`` and runs the base policy to the episode's end, saving every
    decision's state."""
    observation, _ = env.reset(seed=reset_seed)
    decisions: list[tuple] = []
    success, steps = continue_base(
        env, policy, [observation], reset_seed, 0, device, visit=lambda _, obs: decisions.append((env.get_state(), obs))
    )
    return BaseEpisode(reset_seed, success, steps, decisions)


def branch_decision(
    env: PointCloudObservation,
    policy,
    episode: BaseEpisode,
    decision: int,
    generator,
    name: str,
    num_candidates: int,
    device,
) -> tuple[torch.Tensor, list[bool], list[int]]:
    """Every candidate of ``decision`` of ``episode``, each executed from its state and continued with the base
    policy: the chunks ``[K, H, A]``, and each branch's success and steps after the decision. Candidate 0's
    branch is the base episode itself from there, so it is not simulated again."""
    state, observations = episode.decisions[decision]
    chunks = candidate_chunks(
        policy, generator, observations, num_candidates, episode.reset_seed, decision, name, device
    )
    actions = executed_actions(policy, chunks)
    successes, steps = [episode.success], [episode.steps - decision * policy.action_steps]
    for k in range(1, num_candidates):
        won, took = branch(env, policy, state, observations, actions[k], episode.reset_seed, decision, device)
        successes.append(won)
        steps.append(took)
    return chunks, successes, steps
