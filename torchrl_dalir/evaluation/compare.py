"""The base policy and DALI-R on the same evaluation episodes, from their checkpoints."""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import torch
from scipy.stats import binomtest
from tensordict import TensorDictBase

from torchrl_dalir.checkpoints import load_chunk_critic, load_policy, load_world_model
from torchrl_dalir.config import check_at_least, check_probability
from torchrl_dalir.evaluation.success_rate import evaluate
from torchrl_dalir.modules.chunk_critic import ChunkCritic
from torchrl_dalir.modules.receding_horizon import receding_horizon
from torchrl_dalir.reranking import RandomCandidateActor, RerankingActor, RerankingConfig, SearchConfig
from torchrl_dalir.reranking.actor import CANDIDATE_SCORES, CHOSEN_CANDIDATE, check_critic
from torchrl_dalir.reranking.candidates import DropoutPolicy
from torchrl_dalir.reranking.selection import SelectionConfig
from torchrl_dalir.seeds import check_eval_seed

BASE, DALIR, ARGMAX, RANDOM, DROPOUT = (
    "base policy",
    "DALI-R",
    "DALI-R argmax",
    "random candidate",
    "point-dropout policy",
)
METHODS = {
    "base": BASE,
    "dalir": DALIR,
    "argmax": ARGMAX,
    "random": RANDOM,
    "dropout": DROPOUT,
}  # short names for command lines
RERANKING = ("dalir", "argmax", "random")  # the methods that choose among candidates: a world model or a critic
COMMON_NOISE = (
    True  # evaluations sample DALI-R's clean candidate as the base policy does (RerankingActor's common_noise)
)


def evaluation_reranking(reranking: RerankingConfig | None = None, **settings) -> RerankingConfig:
    """The reranking settings of an evaluation: ``reranking`` (by default the paper's,
    :class:`~torchrl_dalir.reranking.RerankingConfig`, with :data:`COMMON_NOISE`), with the
    ``settings`` given (not ``None``) replacing its own, e.g. ``num_candidates=8`` or ``dropout=0.3``.

    Example:
        >>> config = evaluation_reranking(num_candidates=8, search=None)
        >>> config.num_candidates, config.dropout, config.common_noise
        (8, 0.2, True)
    """
    base = reranking if reranking is not None else RerankingConfig(common_noise=COMMON_NOISE)
    return base.updated(**settings)


def check_evaluation_settings(
    episodes: int, seed: int, num_candidates: int = 1, dropout: float = 0.0, *, prefix: str = "", video: int = 0
) -> None:
    """Refuses evaluation settings before any episode runs: fewer than one episode, a negative
    evaluation seed (:func:`~torchrl_dalir.seeds.check_eval_seed`), fewer than one candidate, a
    dropout probability outside ``[0, 1)``, a negative number of videos. ``prefix`` names the
    settings as a job spells them (``eval_`` for ``eval_episodes``, ``eval_seed``)."""
    check_at_least(f"{prefix}episodes", episodes, 1)
    check_eval_seed(seed, f"{prefix}seed")
    check_at_least("num_candidates", num_candidates, 1)
    check_probability("dropout", dropout)
    check_at_least("video", video, 0)


def evaluate_checkpoints(
    policy_path: str | Path,
    world_model_path: str | Path | None = None,
    *,
    episodes: int = 50,
    seed: int = 0,
    device: str = "cpu",
    reranking: RerankingConfig | None = None,
    num_candidates: int | None = None,
    dropout: float | None = None,
    actor_seed: int = 0,
    methods: list[str] | None = None,
    selection: SelectionConfig | None = None,
    common_noise: bool | None = None,
    candidates=None,
    search: SearchConfig | None = None,
    progress: bool = True,
    max_steps: int | None = None,
    video: int = 0,
    video_dir: str | Path | None = None,
    episode_indices: list[int] | None = None,
    stop_when: Callable[[list], bool] | None = None,
    critic: ChunkCritic | str | Path | None = None,
) -> dict[str, dict]:
    """Evaluates a policy checkpoint, and DALI-R on top of it when ``world_model_path`` or ``critic`` is given,
    with 8-of-16 receding-horizon execution on the same ``episodes`` evaluation episodes.

    ``methods`` picks among ``"base"``, ``"dalir"`` (DALI-R choosing by ``selection``, by default
    the rule stored in the world-model checkpoint), ``"argmax"`` (DALI-R with the paper's arg-max
    of the state scorer, whatever the checkpoint names), ``"random"``
    (:class:`RandomCandidateActor`, DALI-R's candidates chosen at random) and ``"dropout"`` (the base
    policy acting on a point-dropout view, :class:`DropoutPolicy`: one perturbed candidate per
    decision, none generated to choose among; it needs no world model); by default the base
    policy, and DALI-R if there is a world model. ``common_noise`` (the default) gives the reranking
    methods' clean candidate the base policy's own sampling noise (common random numbers, see
    :class:`RerankingActor`): keeping it replays the base policy's episode. ``candidates`` (a
    candidate generator, by default the one ``reranking`` names, :class:`PointDropout` ``(dropout)``)
    and ``search`` (an action-space search, by default none) say how the reranking methods make
    their candidates. ``reranking`` (:class:`~torchrl_dalir.reranking.RerankingConfig`, by
    default the paper's settings with common noise, :func:`evaluation_reranking`) holds every
    reranking setting; ``num_candidates``, ``dropout``, ``selection``, ``common_noise`` and
    ``search``, when given, replace its own (``selection=None``: the checkpoint's rule). Returns
    ``{"base policy": {...}, "DALI-R": {...}, ...}``, each with ``success_rate``, ``episodes``,
    ``seconds`` and per-episode ``records``; the reranking methods' records describe their choices
    in ``details`` (:func:`decision_summary`).

    ``max_steps`` stops every episode early (for quick checks). ``video=n`` records the first
    ``n`` episodes of each method as ``<video_dir>/<method>_episode_<i>.gif`` (TorchRL's
    ``VideoRecorder``, see :func:`~torchrl_dalir.evaluation.success_rate.evaluate`), e.g.
    ``base_episode_0.gif`` next to ``dalir_episode_0.gif``: the same episode for each method.
    ``episode_indices`` runs those episodes of ``seed`` instead of the first ``episodes``, and
    ``stop_when`` ends a method's episodes early (both as in
    :func:`~torchrl_dalir.evaluation.success_rate.evaluate`); ``episodes`` in a row is then the number run.
    ``critic`` (a :class:`~torchrl_dalir.modules.ChunkCritic` or its checkpoint, trained on this policy's
    branched outcomes) lets the reranking methods select with ``SelectionConfig(scorer="critic")``; without a
    world model, ``dalir`` and ``random`` rerank with the critic alone (``dalir`` by its arg-max unless
    ``selection`` says otherwise).
    A method that repeats another's row is not run again, so has no videos of its own: ``argmax`` when
    the checkpoint's rule is the arg-max, and, with ``common_noise`` and no ``search``, a DALI-R whose
    rule keeps the clean candidate at every decision (:attr:`SelectionConfig.keeps_clean`, e.g. a
    calibration that kept the base policy): its row is the base policy's episodes, marked
    ``"replays": "base policy"`` and without the per-decision ``details`` (run ``base`` first).
    """
    config = evaluation_reranking(
        reranking,
        num_candidates=num_candidates,
        dropout=dropout,
        selection=selection,
        common_noise=common_noise,
        search=search,
    )
    selection, common_noise, search = config.selection, config.common_noise, config.search
    check_evaluation_settings(episodes, seed, config.num_candidates, config.dropout, video=video)
    if video and video_dir is None:
        raise ValueError(f"video={video} needs video_dir=<folder> for the files")
    reranks = world_model_path is not None or critic is not None
    methods = methods if methods is not None else ["base"] + (["dalir"] if reranks else [])
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown methods {sorted(unknown)}; choose among {sorted(METHODS)}")
    if world_model_path is None and set(methods) & set(RERANKING):
        if critic is None:
            raise ValueError(
                f"methods {sorted(set(methods) & set(RERANKING))} rerank candidates: they need a world_model_path "
                "(or a critic)"
            )
        if "argmax" in methods:
            raise ValueError("method argmax is the paper's scorer on imagined latents: it needs a world_model_path")
    policy = load_policy(policy_path, device)
    if isinstance(critic, (str, Path)):
        critic = load_chunk_critic(critic, device, policy=policy)
    elif critic is not None:
        check_critic(policy, critic)
        critic = critic.to(device)
    if world_model_path is not None:  # fails now, not after the base policy's episodes
        stored = load_world_model(world_model_path, policy=policy).selection
        if "dalir" in methods and selection is None and stored.scorer == "critic" and critic is None:
            raise ValueError(
                f"{world_model_path} stores the rule {stored.name} (calibration_grid=critic): pass critic=<critic.pt> "
                "(the main job's <out>/data/<task>/branched_<policy>_seed<seed>/critic.pt), or selection="
            )
    else:
        stored = SelectionConfig(scorer="critic")
    actors = {"dalir": RerankingActor, "argmax": RerankingActor, "random": RandomCandidateActor}
    rules = {
        "dalir": {"selection": selection} if selection is not None else {},
        "argmax": {"selection": SelectionConfig()},
        "random": {},
    }
    env_kwargs = {"num_points": policy.num_points, "history": policy.config.obs_steps, "device": device}
    if config.decisions > 1:  # the actor counts an episode's decisions by TorchRL's StepCounter
        env_kwargs["step_counter"] = True
    rows, by_rule = {}, {}  # DALI-R with the same rule on the same episodes gives the same row: run it once
    for method in methods:
        if method in ("dalir", "argmax"):
            rule = rules[method].get("selection", stored)
            if rule.name in by_rule:
                rows[METHODS[method]] = by_rule[rule.name]
                continue
            if BASE in rows and replays_base_policy(rule, common_noise, search):
                rows[METHODS[method]] = by_rule[rule.name] = {
                    "selection": rule.name,
                    **rows[BASE],
                    "records": list(rows[BASE]["records"]),
                    "seconds": 0.0,
                    "replays": BASE,
                }
                print(
                    f"[evaluation] {policy.task} {METHODS[method]}: {rule.name} keeps the clean candidate: "
                    "the base policy's episodes",
                    flush=True,
                )
                continue
        start = time.perf_counter()
        if method == "base":
            actor, describe = receding_horizon(policy), None
        elif method == "dropout":
            actor, describe = receding_horizon(DropoutPolicy(policy, config.dropout, actor_seed)), None
        else:
            settings = dict(config=config, seed=actor_seed, candidates=candidates, critic=critic, **rules[method])
            if world_model_path is not None:
                chooser = actors[method].on_policy(policy, world_model_path, device, **settings)
            else:
                chooser = actors[method](policy, **settings)
            actor = receding_horizon(chooser)  # every step carries its decision's scores and choice
            describe = partial(decision_summary, action_steps=policy.config.action_steps)
        name = METHODS[method]
        torch.manual_seed(actor_seed)  # after building the actor, whose modules' initialisation draws from it
        videos = {"video": video, "video_prefix": Path(video_dir) / f"{method}_episode"} if video else {}
        result = evaluate(
            actor,
            policy.task,
            episodes,
            seed,
            progress=progress,
            describe=describe,
            max_steps=max_steps,
            episode_indices=episode_indices,
            stop_when=stop_when,
            **videos,
            **env_kwargs,
        )
        rows[name] = {
            **({"selection": chooser.selection.name} if method in ("dalir", "argmax") else {}),
            "success_rate": result.success_rate,
            "episodes": len(result.episodes),
            "seconds": round(time.perf_counter() - start, 1),
            "records": result.to_dict()["episodes"],
        }
        if method in ("dalir", "argmax"):
            by_rule[rule.name] = rows[name]
        print(
            f"[evaluation] {policy.task} {name}: {result.success_rate:.1%} over {len(result.episodes)} episodes",
            flush=True,
        )
    return rows


def replays_base_policy(
    selection: SelectionConfig, common_noise: bool = True, search: SearchConfig | None = None
) -> bool:
    """Whether DALI-R with ``selection`` plays exactly the base policy's episodes, so need not be
    run: its rule keeps the clean candidate at every decision, which common noise samples as the
    base policy does, and no action-space search replaces the candidates (``search`` is ``None``
    or method ``none``; tested in ``tests/test_common_noise.py``). The replay skips what running
    would check on the way (e.g. that the world model gives finite scores)."""
    return selection.keeps_clean and common_noise and (search is None or search.method == "none")


def paired_sign_test(base: list[bool], dalir: list[bool]) -> dict:
    """Episode-paired comparison of two methods evaluated on the same episodes.

    Only the discordant episodes (one method succeeds, the other fails) carry information about
    the difference; under "no difference" each is equally likely to go either way. Returns the
    counts ``base_only`` and ``dalir_only`` and the exact two-sided binomial (sign-test) p-value.
    """
    if len(base) != len(dalir):
        raise ValueError(f"paired results need the same episodes: {len(base)} vs {len(dalir)}")
    return sign_test(sum(b and not d for b, d in zip(base, dalir)), sum(d and not b for b, d in zip(base, dalir)))


def sign_test(base_only: int, dalir_only: int) -> dict:
    """:func:`paired_sign_test` from the discordant counts alone (e.g. summed over seeds)."""
    n = base_only + dalir_only
    p = float(binomtest(dalir_only, n).pvalue) if n else 1.0
    return {"base_only": base_only, "dalir_only": dalir_only, "p_value": p}


def screen_passed(paired: dict) -> bool:
    """The preregistered screen rule (``docs/results/*_screen_prereg*.json``): a reranker passes its validation
    screen when it wins more of the paired episodes than it loses (``dalir_only > base_only`` of
    :func:`paired_sign_test`). Only a run that passed runs its test episodes."""
    return paired["dalir_only"] > paired["base_only"]


def p_better(base_only: int, dalir_only: int) -> float:
    """The one-sided sign-test p-value of "DALI-R solves more of the paired episodes than the
    base policy", from the discordant counts of :func:`paired_sign_test` (1 without any)."""
    n = base_only + dalir_only
    return float(binomtest(dalir_only, n, alternative="greater").pvalue) if n else 1.0


def decision_summary(rollout: TensorDictBase, action_steps: int) -> dict:
    """DALI-R's choices over one episode (a rollout of ``receding_horizon(RerankingActor(...))``,
    whose steps carry :data:`CANDIDATE_SCORES` and :data:`CHOSEN_CANDIDATE`): the fraction of
    decisions that kept the clean candidate, and the mean over decisions of the clean candidate's
    score, the chosen one's margin over it, and the spread (std) of the candidates' scores. Small
    margins next to the scorer's errors mean the choice is close to random. Decisions the actor did not
    rerank (``RerankingConfig.decisions``; their scores are NaN) are left out: ``decisions`` counts the reranked."""
    decisions = rollout[..., ::action_steps]  # every step repeats its decision's values
    scores, chosen = decisions[CANDIDATE_SCORES].float(), decisions[CHOSEN_CANDIDATE]
    reranked = ~scores.isnan().any(-1)
    scores, chosen = scores[reranked], chosen[reranked]
    clean = scores[..., 0]
    return {
        "decisions": chosen.numel(),
        "clean_chosen": (chosen == 0).float().mean().item(),
        "clean_score": clean.mean().item(),
        "chosen_margin": (scores.gather(-1, chosen.unsqueeze(-1)).squeeze(-1) - clean).mean().item(),
        "score_spread": scores.std(-1).mean().item(),
    }


def pool_decision_summaries(summaries: list[dict]) -> dict:
    """:func:`decision_summary` over many episodes: means weighted by each episode's decisions."""
    total = sum(s["decisions"] for s in summaries)
    pooled = {
        key: sum(s[key] * s["decisions"] for s in summaries) / max(total, 1)
        for key in summaries[0]
        if key != "decisions"
    }
    return {"decisions": total, **pooled}
