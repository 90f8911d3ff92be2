"""Do imagined outcomes rank DALI-R's candidates the way their real outcomes do?

At decisions along base-policy episodes, every candidate's executed actions are run in the
simulator from the same saved state. The scorer then rates the real observation that follows,
next to its rating of the imagined latent. Within one decision, the rank correlation of the two
says whether the world model orders the candidates as the simulator would; the world model's
error, next to how far the candidates' real outcomes lie apart, says whether it can tell them
apart at all. (The scorer's own accuracy on real states is the held-out Brier score's business.)

With ``follow_through``, every candidate's episode then goes on with the base policy to its end,
which says whether the scorer's preferences (on imagined or on real outcomes) point at the
candidates that go on to succeed: the question behind a task where reranking loses.
"""

from __future__ import annotations

from statistics import median

import numpy as np
import torch
from scipy.stats import mannwhitneyu, rankdata, spearmanr
from tqdm.auto import tqdm

from torchrl_dalir.branching.simulator import execute_actions, observation_history, stack_observations
from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
from torchrl_dalir.envs.tasks import TaskSpec, get_task
from torchrl_dalir.reranking.actor import RerankingActor
from torchrl_dalir.seeds import eval_episode_seed


def _base_chunk(policy, observations: list[dict], generator: torch.Generator, device: torch.device) -> np.ndarray:
    """The executed actions of one base-policy chunk (clean observations) after the episode's ``observations``."""
    cloud, agent_pos = observation_history(policy, observations, device)
    chunk = policy.sample(policy.encode(cloud, agent_pos), generator)[0]
    return chunk[policy.config.executed].cpu().numpy()


def _follow_through(
    env: PointCloudObservation, policy, observations: list[dict], generator: torch.Generator, device: torch.device
) -> bool:
    """Runs the base policy after the episode's ``observations`` until the episode ends; whether it succeeded."""
    while True:
        new_observations, success, ended = execute_actions(env, _base_chunk(policy, observations, generator, device))
        if ended:
            return success
        observations = observations + new_observations


@torch.no_grad()
def candidate_outcomes(
    actor: RerankingActor,
    task: str | TaskSpec,
    *,
    episodes: int = 5,
    decisions: int = 10,
    stride: int = 1,
    follow_through: bool = False,
    seed: int = 0,
    progress: bool = True,
    render_every_step: bool = False,
) -> list[dict]:
    """Imagined against real outcomes of every candidate at every ``stride``-th of the first
    ``decisions`` decisions of ``episodes`` evaluation episodes (seeded like
    :func:`~torchrl_dalir.evaluation.evaluate`).

    The episode goes on with the clean candidate (index 0), i.e. along the base policy. Returns
    one record per decision: ``imagined_score`` and ``real_score`` (the scorer on the imagined and
    on the real latent after the executed actions, ``[K]`` each), ``success`` (the candidate
    succeeded within its actions), ``chosen`` (DALI-R's pick), ``rank_correlation`` (Spearman,
    across candidates), ``imagination_error`` (mean L2 between imagined and real latents),
    ``real_spread`` (mean L2 of the real latents from their mean) and ``action_distance`` (``[K]``,
    the L2 distance of each candidate's executed actions from the clean candidate's). With ``follow_through``,
    ``final_success`` ``[K]`` says whether each candidate's episode, continued with the base policy
    (its own seeded noise), succeeded by its end; it costs a rest-of-episode rollout per candidate.
    Clouds are rendered only where a decision or a candidate's outcome reads them (see
    :class:`~torchrl_dalir.envs.gym_env.PointCloudObservation`'s ``decision_period``), which gives
    the same records as ``render_every_step=True`` with fewer renders.
    """
    policy = actor.policy
    spec = get_task(task)
    if spec.name != policy.task:
        raise ValueError(f"the policy was trained on {policy.task!r}, not {spec.name!r}")
    if stride < 1:
        raise ValueError(f"stride must be at least 1, got {stride}")
    device = next(policy.parameters()).device
    base_generator = torch.Generator().manual_seed(actor.seed + 1)  # skipped decisions and follow-throughs
    config = policy.config  # decisions every action_steps steps from the reset, each reading obs_steps observations
    period = 1 if render_every_step else config.action_steps
    env = PointCloudObservation(
        make_simulator(spec), spec, policy.num_points, decision_period=period, history=config.obs_steps
    )
    records = []
    try:
        for episode in tqdm(range(episodes), desc=f"candidate outcomes {spec.name}", disable=not progress, leave=False):
            observation, _ = env.reset(seed=eval_episode_seed(seed, episode))
            observations = [observation]  # the episode's so far
            for decision in range(decisions):
                if decision % stride:
                    clean_observations, _, ended = execute_actions(
                        env, _base_chunk(policy, observations, base_generator, device)
                    )
                else:
                    record, clean_observations, ended = _try_candidates(
                        actor, env, observations, base_generator, follow_through, device
                    )
                    records.append({"episode": episode, "decision": decision, **record})
                if ended:
                    break
                observations = observations + clean_observations
    finally:
        env.close()
    return records


def _try_candidates(
    actor: RerankingActor,
    env: PointCloudObservation,
    observations: list[dict],
    base_generator,
    follow_through: bool,
    device,
):
    """One decision's record after the episode's ``observations``; leaves ``env`` after the clean
    candidate's actions."""
    cloud, agent_pos = observation_history(actor.policy, observations, device)
    chunks, scores = actor.propose(cloud, agent_pos)
    imagined = actor.imagine(cloud, agent_pos, chunks)[0]
    executed = chunks[0, :, actor.policy.config.executed].cpu().numpy()
    start, outcomes, final_success = env.get_state(), [], []
    for k, actions in enumerate(executed):
        env.set_state(start)
        outcome, success, ended = execute_actions(env, actions)
        outcomes.append((outcome, success, ended))
        if k == 0:
            after_clean = env.get_state()
        if follow_through:
            final_success.append(
                success if ended else _follow_through(env, actor.policy, observations + outcome, base_generator, device)
            )
    env.set_state(after_clean)
    real = actor.encoder(*stack_observations([o[-1] for o, _, _ in outcomes], device))
    real_score = torch.sigmoid(actor.scorer(real))
    scores = scores[0].cpu()
    record = {
        "imagined_score": scores.tolist(),
        "real_score": real_score.tolist(),
        "success": [success for _, success, _ in outcomes],
        "chosen": int(scores.argmax()),
        "rank_correlation": float(spearmanr(scores.numpy(), real_score.cpu().numpy()).statistic),
        "imagination_error": float((imagined - real).norm(dim=-1).mean()),
        "real_spread": float((real - real.mean(0)).norm(dim=-1).mean()),
        "action_distance": np.linalg.norm((executed - executed[0]).reshape(len(executed), -1), axis=-1).tolist(),
    }
    if actor.ensemble is not None:  # the scorer ensemble's rating of the same imagined outcomes
        record["ensemble_score"] = torch.sigmoid(actor.ensemble(imagined)).mean(0).tolist()
    if follow_through:
        record["final_success"] = final_success
    clean_observations, _, ended = outcomes[0]
    return record, clean_observations, ended


def within_decision_auc(scores, successes) -> float:
    """The area under the ROC curve of ``scores`` for telling a decision's successful candidates from its
    failed ones (Mann-Whitney U over the decision's (success, failure) pairs; ties count a half),
    averaged over the decisions whose candidates split; NaN if none does. ``scores`` and
    ``successes``: one sequence per decision, ``[K]`` each.

    Example:
        >>> within_decision_auc([[0.9, 0.1, 0.5], [0.2, 0.2], [0.3, 0.7]],
        ...                     [[True, False, False], [True, False], [True, True]])
        0.75
    """
    values = []
    for score, success in zip(scores, successes):
        score, success = np.asarray(score, dtype=float), np.asarray(success, dtype=bool)
        if 0 < success.sum() < len(success):
            values.append(mannwhitneyu(score[success], score[~success]).statistic / (success.sum() * (~success).sum()))
    return float(np.mean(values)) if values else float("nan")


def summarize_candidate_outcomes(records: list[dict]) -> dict:
    """Medians over decisions; how DALI-R's pick ranks among the candidates' real scores; at
    decisions where only some candidates finish the task within their actions, how often the pick
    does against the candidates' average (chance); whether extreme scores go to the candidates
    that moved furthest (:func:`_extreme_score_distance_correlation`); and, with follow-through
    records, :func:`_follow_through_summary`."""
    correlations = [r["rank_correlation"] for r in records if np.isfinite(r["rank_correlation"])]
    # The pick's percentile among the other candidates' real scores: 1 best, 0 worst, 0.5 chance.
    percentiles = [
        sum(s < r["real_score"][r["chosen"]] for s in r["real_score"]) / max(len(r["real_score"]) - 1, 1)
        for r in records
    ]
    # Decisions where some candidates, not all, finish the task within their actions.
    split = [r for r in records if 0 < sum(r["success"]) < len(r["success"])]
    return {
        "decisions": len(records),
        "median_rank_correlation": median(correlations) if correlations else float("nan"),
        "median_imagined_std": median(float(np.std(r["imagined_score"])) for r in records),
        "median_real_std": median(float(np.std(r["real_score"])) for r in records),
        "median_error_over_spread": median(r["imagination_error"] / max(r["real_spread"], 1e-12) for r in records),
        "mean_pick_percentile": float(np.mean(percentiles)),
        "pick_real_score_gain": float(
            np.mean([r["real_score"][r["chosen"]] - np.mean(r["real_score"]) for r in records])
        ),
        "decisions_some_candidates_succeed": len(split),
        "pick_succeeds_there": float(np.mean([r["success"][r["chosen"]] for r in split])) if split else float("nan"),
        "candidates_succeed_there": float(np.mean([np.mean(r["success"]) for r in split])) if split else float("nan"),
        **(
            {"extreme_score_distance_correlation": _extreme_score_distance_correlation(records)}
            if all("action_distance" in r for r in records)
            else {}
        ),
        **_follow_through_summary([r for r in records if "final_success" in r]),
    }


def _extreme_score_distance_correlation(records: list[dict]) -> float:
    """Median over decisions of the Spearman correlation, across the perturbed candidates, between
    how far a candidate's imagined score lies from the decision's median score and how far its
    actions lie from the clean candidate's: positive when the extreme scores go to the candidates
    that moved furthest, i.e. where the world model and scorer extrapolate."""
    values = []
    for r in records:
        scores, distance = np.asarray(r["imagined_score"][1:]), np.asarray(r["action_distance"][1:])
        extremity = np.abs(scores - np.median(scores))
        if len(scores) > 2 and np.ptp(extremity) > 0 and np.ptp(distance) > 0:  # else the correlation is undefined
            values.append(spearmanr(extremity, distance).statistic)
    return median(values) if values else float("nan")


def success_by_score_rank(records: list[dict], score: str = "imagined_score", bins: int = 4) -> list[float]:
    """How often a candidate's episode went on to succeed (``final_success``), by the rank of its
    ``score`` within its decision, in ``bins`` groups of rank positions from the lowest scores to
    the highest (position ``p`` of ``K`` falls in group ``p * bins // K``): flat when the score
    tells nothing, rising when it orders the candidates, and falling at both ends when its
    extremes mark candidates it misjudges. Candidates with tied scores share their positions
    evenly, so ties favour no candidate (all-equal scores spread every candidate over all groups).
    Every decision needs at least ``bins`` candidates."""
    if bins < 1:
        raise ValueError(f"bins must be at least 1, got {bins}")
    successes, counts = np.zeros(bins), np.zeros(bins)
    for r in records:
        scores, success = np.asarray(r[score], dtype=float), np.asarray(r["final_success"], dtype=float)
        if len(scores) < bins:
            raise ValueError(f"a decision has {len(scores)} candidates, fewer than bins={bins}")
        group_of_position = np.arange(len(scores)) * bins // len(scores)
        # a candidate and those tied with it hold positions first .. last - 1 (0: the lowest score)
        firsts, lasts = rankdata(scores, "min").astype(int) - 1, rankdata(scores, "max").astype(int)
        for first, last, succeeded in zip(firsts, lasts, success):
            weight = np.bincount(group_of_position[first:last], minlength=bins) / (last - first)
            successes += weight * succeeded
            counts += weight
    return [float(s / c) if c else float("nan") for s, c in zip(successes, counts)]


def _follow_through_summary(records: list[dict]) -> dict:
    """How often the episode, continued with the base policy, succeeds after the clean candidate,
    DALI-R's pick, an average candidate (a random pick), and the candidate whose real outcome the
    scorer rates best (DALI-R with perfect imagination); and, at decisions where only some
    candidates go on to succeed, the area under the ROC curve of each score (imagined, real, and the
    scorer ensemble's on the imagined outcome where the world model has one) for telling them
    apart (0.5: no better than chance); and the success by score quarter
    (:func:`success_by_score_rank`)."""
    if not records:
        return {}

    def rate(pick) -> float:
        return float(np.mean([r["final_success"][pick(r)] for r in records]))

    split = [r for r in records if 0 < sum(r["final_success"]) < len(r["final_success"])]

    def auc(score: str) -> float:
        return within_decision_auc([r[score] for r in split], [r["final_success"] for r in split])

    return {
        "final_success_clean": rate(lambda r: 0),
        "final_success_pick": rate(lambda r: r["chosen"]),
        "final_success_average_candidate": float(np.mean([np.mean(r["final_success"]) for r in records])),
        "final_success_real_best": rate(lambda r: int(np.argmax(r["real_score"]))),
        "decisions_split_by_final_success": len(split),
        "imagined_score_auc_there": auc("imagined_score"),
        "real_score_auc_there": auc("real_score"),
        **({"ensemble_score_auc_there": auc("ensemble_score")} if all("ensemble_score" in r for r in records) else {}),
        "final_success_by_imagined_score_quarter": success_by_score_rank(records),
        **(
            {"final_success_by_ensemble_score_quarter": success_by_score_rank(records, "ensemble_score")}
            if all("ensemble_score" in r for r in records)
            else {}
        ),
    }
