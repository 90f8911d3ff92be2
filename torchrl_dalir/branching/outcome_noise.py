"""Is a candidate's branched outcome a property of its chunk, or of the noise that follows it?

The branched outcomes (:mod:`~torchrl_dalir.branching.outcomes`) and the candidates' ceiling
(:mod:`~torchrl_dalir.branching.ceiling`) continue every candidate with the base policy
under one draw of its sampling noise (common random numbers). An oracle that picks a winner of that
draw knows the future noise; a scorer of the state and the chunk cannot. Here each stored candidate is
executed again from the same saved state and continued under *another* draw of the base policy's noise:
if the first draw's winners win again more often than its losers, the chunk carries signal a scorer can
learn; if not, the first draw's winners were luck, and no scorer can reach that ceiling.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from torchrl_dalir import keys
from torchrl_dalir.branching.candidate_outcomes import within_decision_auc
from torchrl_dalir.branching.outcomes import DECISION, RESET_SEED, SUCCESS, BranchedOutcomes
from torchrl_dalir.branching.simulator import (
    base_decisions,
    branch,
    executed_actions,
    observation_history,
)
from torchrl_dalir.data.storage import _read_json
from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
from torchrl_dalir.envs.tasks import get_task
from torchrl_dalir.objectives.within_state_ranking import split_decisions
from torchrl_dalir.utils import atomic_write, weights_digest

# Draw d > 0 of the base policy's noise after a decision uses the noise stream of episode seed
# reset_seed + d * NOISE_DRAW_STRIDE (draw 0 is the collection's own), far from any real reset seed.
NOISE_DRAW_STRIDE = 2**40


def noise_seed(reset_seed: int, draw: int) -> int:
    """The seed of the base policy's noise stream in draw ``draw`` after a decision of episode ``reset_seed``."""
    return reset_seed + draw * NOISE_DRAW_STRIDE


def decision_state(env: PointCloudObservation, policy, reset_seed: int, decision: int, device) -> tuple:
    """The simulator state and the observations at ``decision`` of the base episode reset with ``reset_seed``
    (the base policy's own chunks before it, as in :func:`~torchrl_dalir.branching.simulator.base_episode`)."""
    reached = list(base_decisions(env, policy, reset_seed, decision + 1, device))
    if len(reached) <= decision:
        raise ValueError(f"the base episode of reset seed {reset_seed} ended before decision {decision}")
    return env.get_state(), reached[-1]


def replayed_decisions(policy, task: str, rows: TensorDict, desc: str, progress: bool, device) -> Iterator[tuple]:
    """For each branched row, ``(row, env, state, observations)`` at its decision, replayed by
    :func:`decision_state` in one simulator of ``task`` that is closed at the end."""
    spec = get_task(task)
    env = PointCloudObservation(
        make_simulator(spec), spec, policy.num_points, decision_period=policy.action_steps, history=policy.obs_steps
    )
    try:
        for row in tqdm(rows, desc=f"{desc} {spec.name}", disable=not progress):
            yield row, env, *decision_state(env, policy, int(row[RESET_SEED]), int(row[DECISION]), device)
    finally:
        env.close()


@torch.no_grad()
def privileged_states(
    policy, outcomes: BranchedOutcomes | TensorDict, progress: bool = True, device="cpu"
) -> torch.Tensor:
    """The simulator's low-dimensional state ``[D, S]`` (``privileged_state``: what the experts read) at each
    decision of branched ``outcomes`` (a collection or a table of its rows), replayed from the row's reset seed
    and decision as :func:`decision_state` does. The replayed observation history must equal the stored one bit
    for bit (else the replay is not the branched episode, and this refuses it). For a teacher's training only:
    nothing at test time reads simulator state."""
    rows = outcomes.rows.to_tensordict() if hasattr(outcomes, "rows") else outcomes
    task = outcomes.meta.task if hasattr(outcomes, "meta") else policy.task
    states = []
    for row, _, _, observations in replayed_decisions(policy, task, rows, "replay", progress, device):
        cloud, agent_pos = observation_history(policy, observations, "cpu")
        if not (torch.equal(cloud[0], row[keys.POINT_CLOUD]) and torch.equal(agent_pos[0], row[keys.AGENT_POS])):
            raise ValueError(
                f"replaying reset seed {int(row[RESET_SEED])} to decision {int(row[DECISION])} does not give the "
                "stored observation: another policy, task or simulator version than the branched collection's"
            )
        states.append(torch.as_tensor(observations[-1][keys.PRIVILEGED_STATE], dtype=torch.float32))
    return torch.stack(states)


@torch.no_grad()
def redraw_outcomes(
    policy,
    outcomes: BranchedOutcomes,
    draw: int = 1,
    only_split: bool = True,
    progress: bool = True,
    device="cpu",
    resume: str | Path | None = None,
) -> TensorDict:
    """Every stored candidate of ``outcomes``' decisions (those that split, with ``only_split``) executed again
    from its saved state and continued with the base policy under noise draw ``draw`` (0: the collection's
    own, which reproduces the stored outcomes). Returns the decisions' rows with ``success`` ``[D, K]`` of the
    new draw and ``first_success``, the stored one.

    With ``resume`` (a JSON file), each finished decision's outcomes are written to it as they come (atomically),
    and a call that finds it continues at the first unfinished decision: a killed redraw of an hour loses one
    decision, and gives the same outcomes. The file names its plan (the policy's weights, the collection, the
    draw, ``only_split``); one of another plan is refused."""
    rows = outcomes.rows.to_tensordict()
    if only_split:
        rows = rows[split_decisions(rows[SUCCESS])]
    plan = {
        "policy_digest": weights_digest(policy),
        "collection": outcomes.meta.plan(),
        "draw": draw,
        "only_split": only_split,
        "decisions": len(rows),
    }
    successes = _resumed(Path(resume), plan) if resume is not None else []
    for row, env, state, observations in replayed_decisions(
        policy, outcomes.meta.task, rows[len(successes) :], "redraw", progress, device
    ):
        reset_seed, decision = int(row[RESET_SEED]), int(row[DECISION])
        actions = executed_actions(policy, row[keys.ACTION_CHUNK])
        seed = noise_seed(reset_seed, draw)
        successes.append(
            [bool(branch(env, policy, state, observations, a, seed, decision, device)[0]) for a in actions]
        )
        if resume is not None:
            atomic_write(resume, json.dumps({"plan": plan, "success": successes}))
    out = rows.select(RESET_SEED, DECISION).clone()
    out.set("first_success", rows[SUCCESS])
    out.set(SUCCESS, torch.tensor(successes, dtype=torch.bool).reshape(rows[SUCCESS].shape))
    return out


def _resumed(path: Path, plan: dict) -> list[list[bool]]:
    """The finished decisions' outcomes in a redraw's ``resume`` file (none if there is no file yet)."""
    if not path.exists():
        return []
    stored = _read_json(path)
    if stored.get("plan") != plan:
        raise ValueError(
            f"{path} holds the redraw of another plan ({stored.get('plan')}), not {plan}: "
            "choose another file or delete it"
        )
    return [[bool(s) for s in row] for row in stored["success"]]


def oracle_pick(success: torch.Tensor) -> torch.Tensor:
    """The candidate the ceiling's oracle executes at each decision ``[D, K]``: the clean one if it won (or none
    won), else the first winner."""
    won = success.clone()
    won[:, 0] |= ~success.any(-1)
    return won.float().argmax(-1)


def repeatability(first: torch.Tensor, second: torch.Tensor) -> dict:
    """How far the first draw's outcomes ``[D, K]`` predict the second's: the chance to win again after a win and
    after a loss, the within-decision AUC of the first outcome as a score of the second, and the second draw's
    success rate of the clean candidate, of a random candidate, of the first draw's oracle pick, and of a winner
    of the second draw wherever there is one."""
    first, second = first.bool(), second.bool()
    pick = second.gather(-1, oracle_pick(first).unsqueeze(-1)).squeeze(-1)
    return {
        "decisions": len(first),
        "win_again": float(second[first].float().mean()) if first.any() else float("nan"),
        "win_after_loss": float(second[~first].float().mean()) if (~first).any() else float("nan"),
        "auc_of_first_draw": within_decision_auc(first.float().tolist(), second.tolist()),
        "second_draw_split": int(split_decisions(second).sum()),
        "clean": float(second[:, 0].float().mean()),
        "random": float(second.float().mean()),
        "first_draw_oracle_pick": float(pick.float().mean()),
        "second_draw_oracle": float(second.any(-1).float().mean()),
        "first_draw_oracle": float(first.any(-1).float().mean()),
        "first_draw_clean": float(first[:, 0].float().mean()),
    }


def honest_ceiling(success: torch.Tensor) -> dict:
    """The gain a scorer that knows each chunk's true chance could reach, from outcomes ``[D, K, M]`` of every
    candidate of ``D`` decisions under ``M >= 2`` independent draws of the base policy's noise after the chunk.

    Cross-fitted over draws: for each held-out draw ``m`` the pick is the candidate with the best mean outcome
    over the other ``M - 1`` draws (ties go to the lowest index, so the clean candidate 0 first), and it is
    judged on draw ``m`` alone. Unlike the clairvoyant oracle (a winner of the draw that is judged), it cannot
    pick the lucky continuation. Returns, averaged over the held-out draws and all ``D`` decisions: the success
    rate of the clean candidate, a random candidate, the honest pick and the clairvoyant oracle, the honest gain
    over the clean candidate with its standard error over decisions, and the within-decision AUC of the other
    draws' mean as a score of the held-out outcome (at the decisions that split in the held-out draw).

    Example:
        >>> success = torch.tensor([[[0, 0, 0, 1], [1, 1, 1, 0]],    # candidate 1 wins 3 draws of 4
        ...                         [[1, 1, 0, 0], [1, 1, 0, 0]]])   # the same chance: nothing to gain
        >>> {k: honest_ceiling(success)[k] for k in ("clean", "honest", "oracle", "honest_gain")}
        {'clean': 0.375, 'honest': 0.625, 'oracle': 0.75, 'honest_gain': 0.25}
    """
    if success.dim() != 3 or success.shape[-1] < 2:
        raise ValueError(
            f"success must be [decisions, candidates, draws] with at least 2 draws, got {tuple(success.shape)}"
        )
    success = success.bool()
    draws = success.shape[-1]
    picked, chance_scores, held_out = [], [], []
    for m in range(draws):
        others = [d for d in range(draws) if d != m]
        chance = success[..., others].float().mean(-1)  # [D, K]: the candidates' estimated chance
        pick = chance.argmax(-1, keepdim=True)  # the first of the best: candidate 0 on a tie with it
        picked.append(success[..., m].gather(-1, pick).squeeze(-1).float())
        chance_scores += chance.tolist()
        held_out += success[..., m].tolist()
    clean = float(success[:, 0].float().mean())
    honest = float(torch.stack(picked).mean())
    gains = torch.stack(picked).mean(0) - success[:, 0].float().mean(-1)  # [D]: each decision's honest gain
    se = float(gains.std() / len(gains) ** 0.5) if len(gains) > 1 else float("nan")
    return {
        "decisions": len(success),
        "candidates": success.shape[1],
        "draws": draws,
        "clean": clean,
        "random": float(success.float().mean()),
        "honest": honest,
        "oracle": float(success.any(1).float().mean()),
        "honest_gain": honest - clean,
        "honest_gain_se": se,
        "oracle_gain": float(success.any(1).float().mean()) - clean,
        "true_chance_auc": within_decision_auc(chance_scores, held_out),
    }


def honest_ceiling_by_decision(success: torch.Tensor, decision: torch.Tensor) -> dict[int, dict]:
    """:func:`honest_ceiling` apart at each decision index of the episodes: where in an episode the candidates
    have headroom. ``decision`` ``[D]`` is each row's decision index (its ``decision`` entry); each index's
    gain is that of reranking it alone, the base policy acting at the others.

    Example:
        >>> success = torch.tensor([[[0, 0], [1, 1]], [[1, 1], [1, 1]]])  # decision 0 of one episode, 1 of it
        >>> {d: c["honest_gain"] for d, c in honest_ceiling_by_decision(success, torch.tensor([0, 1])).items()}
        {0: 1.0, 1: 0.0}
    """
    if decision.shape != success.shape[:1]:
        raise ValueError(
            f"decision must give each of the {len(success)} rows its index, got shape {tuple(decision.shape)}"
        )
    return {int(d): honest_ceiling(success[decision == d]) for d in decision.unique().tolist()}


def honest_ceiling_by_candidates(success: torch.Tensor) -> dict[int, dict]:
    """:func:`honest_ceiling` with the first ``k`` candidates only, for ``k = 2, 4, 8, ...`` below ``K`` and ``K``
    itself: how the headroom grows with the candidates drawn from the same states (candidate 0 is the clean one,
    the others are independent draws, so the first ``k`` are a draw of ``k`` candidates).

    Example:
        >>> success = torch.tensor([[[0, 0], [0, 0], [1, 1], [0, 0]]])  # only candidate 2 wins
        >>> {k: c["honest_gain"] for k, c in honest_ceiling_by_candidates(success).items()}
        {2: 0.0, 4: 1.0}
    """
    counts = [2**i for i in range(1, success.shape[1].bit_length()) if 2**i < success.shape[1]] + [success.shape[1]]
    return {k: honest_ceiling(success[:, :k]) for k in counts}


__all__ = [
    "NOISE_DRAW_STRIDE",
    "decision_state",
    "honest_ceiling",
    "honest_ceiling_by_candidates",
    "honest_ceiling_by_decision",
    "noise_seed",
    "oracle_pick",
    "privileged_states",
    "redraw_outcomes",
    "repeatability",
]
