"""The candidates' ceiling: how often a perfect choice among a decision's candidates succeeds.

A measurement in the simulator, never a method. At every decision of a base-policy episode, each
candidate chunk is executed from the saved simulator state and the episode is continued with the
base policy to its end (rollout-based policy improvement, Tesauro and Galperin 1996). The oracle
executes a candidate whose branch succeeded (ties: the clean candidate, then the earliest
success). Its success rate is that of one step of policy improvement with a perfect judge of each
candidate's outcome under the base policy: what a scorer that knows those outcomes reaches. It is
not a bound on every chooser: one that leaves the clean candidate at several decisions, none of
which succeeds alone under the base policy, can succeed where the oracle fails.

Common random numbers make this cheap and exact (:mod:`~torchrl_dalir.branching.simulator`): the
clean candidate's branch from decision ``j`` *is* the base episode from there on, and after the
oracle executes a winning candidate its next clean candidate replays that winning branch. The
oracle's episode therefore succeeds exactly when the base
episode succeeds or, at some decision along it, a candidate's branch succeeds; it follows the
base episode until the first such decision. Only failed base episodes are branched, and each
generator's search stops at the first decision with a winning branch (``exhaustive=True`` runs
every branch of every decision instead, to count the decisions whose candidates split).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import torch
from tqdm.auto import tqdm

from torchrl_dalir.branching.simulator import base_episode, branch_decision
from torchrl_dalir.config import check_at_least
from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
from torchrl_dalir.envs.tasks import TaskSpec, get_task
from torchrl_dalir.evaluation.calibration import TEST_SEED
from torchrl_dalir.seeds import eval_episode_seed


def oracle_choice(successes: list[bool], steps: list[int]) -> int | None:
    """The candidate the oracle executes: the clean one (0) if its branch succeeded, else the branch that
    succeeded soonest (the lowest index among equals), else none."""
    if successes[0]:
        return 0
    winners = [k for k, won in enumerate(successes) if won]
    return min(winners, key=lambda k: (steps[k], k)) if winners else None


def ceiling_episode(
    env: PointCloudObservation,
    policy,
    generators: dict[str, object],
    episode_seed: int,
    num_candidates: int = 8,
    exhaustive: bool = False,
    stride: int = 1,
    device="cpu",
) -> dict:
    """One episode: the base policy's outcome and, per generator, the oracle's (see the module docstring).
    With ``stride > 1`` the oracle chooses only at every ``stride``-th decision (and keeps the base
    policy's chunk at the others): a lower bound on the every-decision ceiling, at ``1 / stride`` of the cost."""
    device = torch.device(device)
    episode = base_episode(env, policy, episode_seed, device)
    base_success, base_steps, decisions = episode.success, episode.steps, episode.decisions
    record = {
        "reset_seed": episode_seed,
        "base_success": base_success,
        "base_steps": base_steps,
        "decisions": len(decisions),
        "generators": {},
    }
    for name, generator in generators.items():
        outcome = {
            "success": base_success,
            "decision": 0 if base_success else None,
            "candidate": 0 if base_success else None,
            "steps": base_steps if base_success else None,
            "branches": 0,
            "winners": None,
        }
        if exhaustive:
            outcome["branch_successes"] = []
        if not base_success or exhaustive:
            for j in range(len(decisions)):
                if j % stride:
                    continue
                _, successes, steps = branch_decision(env, policy, episode, j, generator, name, num_candidates, device)
                outcome["branches"] += num_candidates - 1
                if exhaustive:
                    outcome["branch_successes"].append(successes)
                chosen = oracle_choice(successes, steps)
                if chosen is not None and outcome["decision"] in (None, j):
                    outcome.update(
                        success=True,
                        decision=j,
                        candidate=chosen,
                        winners=sum(successes),
                        steps=j * policy.action_steps + steps[chosen],
                    )
                    if not exhaustive:
                        break
        record["generators"][name] = outcome
    return record


def candidate_ceiling(
    policy,
    task: str | TaskSpec,
    generators: dict[str, object],
    *,
    episodes: int = 20,
    seed: int = 1,
    num_candidates: int = 8,
    exhaustive: bool = False,
    stride: int = 1,
    done: Iterable[int] = (),
    on_episode: Callable[[dict], None] | None = None,
    progress: bool = True,
    device="cpu",
) -> list[dict]:
    """The ceiling over ``episodes`` evaluation episodes of evaluation ``seed`` (a validation seed; the
    test seed is refused): a record per episode (:func:`ceiling_episode`, plus ``episode``). Episodes in
    ``done`` are skipped (resumption); ``on_episode`` receives each new record as soon as it is finished."""
    spec = get_task(task)
    if policy.task is not None and spec.name != policy.task:
        raise ValueError(f"the policy was trained on {policy.task!r}, not {spec.name!r}")
    if num_candidates < 2:
        raise ValueError(f"num_candidates must be at least 2 (the clean candidate and one more), got {num_candidates}")
    check_at_least("stride", stride, 1)
    if seed == TEST_SEED:
        raise ValueError(f"seed={TEST_SEED} holds the test episodes; measure the ceiling on validation episodes")
    env = PointCloudObservation(
        make_simulator(spec), spec, policy.num_points, decision_period=policy.action_steps, history=policy.obs_steps
    )
    done, records = set(done), []
    try:
        todo = [e for e in range(episodes) if e not in done]
        for episode in tqdm(todo, desc=f"ceiling {spec.name}", disable=not progress):
            record = {
                "episode": episode,
                **ceiling_episode(
                    env,
                    policy,
                    generators,
                    eval_episode_seed(seed, episode),
                    num_candidates,
                    exhaustive,
                    stride,
                    device,
                ),
            }
            records.append(record)
            if on_episode is not None:
                on_episode(record)
    finally:
        env.close()
    return records


def summarize_ceiling(records: list[dict]) -> dict:
    """Success rates of the base policy and of the oracle per generator, over the episodes of ``records``;
    the failures each generator fixes; and, with exhaustive records, how many decisions split."""
    base = [r["base_success"] for r in records]
    summary = {
        "episodes": len(records),
        "base_successes": int(sum(base)),
        "base_success_rate": float(np.mean(base)) if base else float("nan"),
        "generators": {},
    }
    for name in records[0]["generators"] if records else ():
        outcomes = [r["generators"][name] for r in records]
        fixed = [o for o, r in zip(outcomes, records) if o["success"] and not r["base_success"]]
        entry = {
            "oracle_successes": int(sum(o["success"] for o in outcomes)),
            "oracle_success_rate": float(np.mean([o["success"] for o in outcomes])),
            "failures_fixed": len(fixed),
            "failures": int(len(records) - sum(base)),
            "median_fix_decision": float(np.median([o["decision"] for o in fixed])) if fixed else None,
            "median_winners_at_fix": float(np.median([o["winners"] for o in fixed])) if fixed else None,
            "branches": int(sum(o["branches"] for o in outcomes)),
        }
        entry["headroom"] = entry["oracle_success_rate"] - summary["base_success_rate"]
        split = [s for o in outcomes for s in o.get("branch_successes", []) if 0 < sum(s) < len(s)]
        if any("branch_successes" in o for o in outcomes):
            entry["decisions_split"] = len(split)
            entry["decisions_branched"] = sum(len(o["branch_successes"]) for o in outcomes)
        summary["generators"][name] = entry
    return summary
