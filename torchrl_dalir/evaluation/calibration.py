"""Calibrating DALI-R's selection rule on validation episodes, and storing it in the checkpoint.

Every setting of a rule (the margin, the pessimism ``k``, the temperature) is chosen on
*validation* episodes, which have their own evaluation seed, and never on the test episodes
that results report. The base policy and every rule of the grid run on the same validation
episodes. The grids list the most conservative setting first, ``margin=1``, which always
executes the clean candidate (with common noise, the default, the base policy's own chunk: the
base policy's episodes exactly). Another entry is eligible only with evidence that it beats the
base policy on these episodes (a one-sided sign test on the paired episodes, p <= ``alpha``), and
the winner is the eligible entry with the most successes (among those of ``rule`` if one is
named), ties going to the entry listed first. Without the evidence rule (``alpha=1``) the best of
nine settings on 30 episodes is largely luck; with it, DALI-R stays the base policy unless the
scorer's choices helped visibly. The choice is written into the world-model checkpoint, so
:meth:`RerankingActor.from_checkpoints` uses it with no argument.
"""

from __future__ import annotations

from pathlib import Path

from torchrl_dalir.checkpoints import load_world_model, store_selection
from torchrl_dalir.config import check_at_least
from torchrl_dalir.evaluation.compare import (
    BASE,
    DALIR,
    evaluate_checkpoints,
    evaluation_reranking,
    p_better,
    paired_sign_test,
    replays_base_policy,
)
from torchrl_dalir.reranking.selection import SelectionConfig

TEST_SEED = 0  # the evaluation seed of the episodes that results report
VALIDATION_SEED = 1
# The evidence an entry needs to be chosen over the most conservative one: the one-sided sign-test
# p-value of "it solves more validation episodes than the base policy" (0.1 on 30 episodes: e.g.
# 4 episodes won and none lost, or 7 won and 1 lost). Fixed before the test episodes were run.
ALPHA = 0.1

# The default rule's settings, most conservative first: margin 1 never leaves the clean
# candidate (probabilities differ by less than 1), i.e. it is the base policy.
MARGIN_GRID = tuple(SelectionConfig("margin", "ensemble", k=1.0, margin=m) for m in (1.0, 0.05, 0.02, 0.01, 0.0))
# Other rules, evaluated on the same validation episodes for comparison.
COMPARISON_GRID = (
    SelectionConfig("argmax", "state"),  # the paper
    SelectionConfig("argmax", "ensemble"),
    SelectionConfig("pessimistic", "ensemble", k=1.0),
    SelectionConfig("softmax", "ensemble", temperature=0.01),
)
# One alternative to the base policy, named before any episode: with a single comparison the
# sign test's p-value needs no correction for the best-of-nine choice (the winner's curse), and the
# calibration runs two entries instead of nine.
ARGMAX_GRID = (MARGIN_GRID[0], SelectionConfig("argmax", "ensemble"))
# One alternative as well: the arg-max of a chunk critic trained on branched outcomes (needs critic=).
CRITIC_GRID = (MARGIN_GRID[0], SelectionConfig("argmax", "critic"))
GRIDS = {
    "margin": MARGIN_GRID,
    "all": MARGIN_GRID + COMPARISON_GRID,
    "argmax": ARGMAX_GRID,
    "critic": CRITIC_GRID,
}  # by name, for configurations
# calibrate_on_failures: the base policy's validation failures that the screen waits for (10:
# 4 won and none lost is then possible, and 7 / 1), the fewest and the most episodes it runs, and
# the episodes between two looks at the count.
FAILURES = 10
MIN_EPISODES = 30  # the fixed design's count: the confirmation, as long as the screen, never runs fewer
MAX_EPISODES = 150
BLOCK = 10
DESIGNS = ("fixed", "failures")  # calibrate: every entry on a fixed number of episodes | calibrate_on_failures


def calibrate(
    policy_path: str | Path,
    world_model_path: str | Path,
    *,
    grid: tuple[SelectionConfig, ...] = GRIDS["all"],
    rule: str | None = None,
    episodes: int = 30,
    seed: int = VALIDATION_SEED,
    test_seed: int = TEST_SEED,
    write: bool = True,
    alpha: float = ALPHA,
    confirm_episodes: int = 0,
    confirm_seed: int | None = None,
    **evaluate_kwargs,
) -> dict:
    """Evaluates the base policy and every entry of ``grid`` on ``episodes`` validation episodes
    of evaluation seed ``seed``, picks an entry with :func:`choose` and, if ``write``,
    stores it in the world-model checkpoint (``selection``, with the whole record under
    ``calibration``). Returns that record: per entry its name, settings, success rate, the
    paired comparison with the base policy, and the chosen entry. An entry that keeps the clean
    candidate at every decision (margin 1) is the base policy's episodes under common noise
    (:func:`~torchrl_dalir.evaluation.compare.replays_base_policy`) and is not run again.
    ``evaluate_kwargs`` go to :func:`~torchrl_dalir.evaluation.compare.evaluate_checkpoints`, e.g.
    ``reranking=RerankingConfig(num_candidates=16)`` (every entry's candidates; the entry is the rule).

    With ``confirm_episodes > 0`` a chosen entry other than the most conservative one must win
    again on ``confirm_episodes`` fresh validation episodes (evaluation seed ``confirm_seed``,
    by default ``seed + 1``), against the base policy with the same one-sided p-value bar;
    otherwise the most conservative entry is kept. The best of nine entries on the same 30
    episodes clears a per-entry bar by luck far more often than ``alpha`` (the winner's curse);
    a second draw does not share that luck. The record's ``confirmation`` says what happened.

    Raises ``ValueError`` for the test seed ``test_seed`` (as ``seed`` or ``confirm_seed``), for a
    ``rule`` that no grid entry has, for ``alpha`` outside (0, 1], and for ensemble rules on a
    world model without a scorer ensemble, before any episode.
    """
    confirm_seed = seed + 1 if confirm_seed is None else confirm_seed
    _check_calibration(
        world_model_path,
        grid,
        rule,
        alpha,
        seed,
        test_seed,
        confirm_seed if confirm_episodes else None,
        evaluate_kwargs.get("critic"),
    )
    common = dict(episodes=episodes, seed=seed, **evaluate_kwargs)
    base = evaluate_checkpoints(policy_path, world_model_path, methods=["base"], **common)[BASE]
    base_successes = [r["success"] for r in base["records"]]
    entries = []
    for entry in grid:
        if _replays_base_policy(entry, evaluate_kwargs):
            row = {**base, "seconds": 0.0}  # margin 1: the base policy's episodes, not run again
        else:
            row = evaluate_checkpoints(policy_path, world_model_path, methods=["dalir"], selection=entry, **common)[
                DALIR
            ]
        successes = [r["success"] for r in row["records"]]
        entries.append(
            {
                "name": entry.name,
                "selection": entry.to_dict(),
                "success_rate": row["success_rate"],
                "vs_base": paired_sign_test(base_successes, successes),
                "seconds": row["seconds"],
            }
        )
    chosen = choose(entries, rule, alpha)
    conservative = family(entries, rule)[0]
    confirmation = None
    if confirm_episodes and chosen is not conservative:
        confirmation = _confirm(
            policy_path, world_model_path, chosen, confirm_episodes, confirm_seed, alpha, **evaluate_kwargs
        )
        chosen = chosen if confirmation["confirmed"] else conservative
    record = {
        "episodes": episodes,
        "seed": seed,
        "rule": rule,
        "alpha": alpha,
        "base_success_rate": base["success_rate"],
        "entries": entries,
        **({"confirmation": confirmation} if confirmation else {}),
        "chosen": chosen["name"],
        "selection": chosen["selection"],
    }
    if write:
        store_selection(world_model_path, SelectionConfig(**chosen["selection"]), record)
    return record


def calibrate_on_failures(
    policy_path: str | Path,
    world_model_path: str | Path,
    *,
    grid: tuple[SelectionConfig, ...] = GRIDS["all"],
    rule: str | None = None,
    failures: int = FAILURES,
    min_episodes: int = MIN_EPISODES,
    max_episodes: int = MAX_EPISODES,
    block: int = BLOCK,
    seed: int = VALIDATION_SEED,
    confirm_seed: int | None = None,
    test_seed: int = TEST_SEED,
    alpha: float = ALPHA,
    write: bool = True,
    **evaluate_kwargs,
) -> dict:
    """Calibration sized by the base policy's failures rather than by a fixed number of episodes.

    A rule can only gain where the base policy fails, so a fixed 30 episodes on which it fails
    three times cannot show a gain however real. Here:

    1. *Screen.* The base policy runs validation episodes of evaluation seed ``seed``, ``block``
       at a time, until it has run ``min_episodes`` and failed ``failures`` times (at most
       ``max_episodes``). Every entry
       of ``grid`` (but the most conservative, the base policy itself) then runs on the episodes
       it failed and on as many it solved (the first ones): its estimated gain in success rate
       is the share of those failures it solves times the base policy's failure rate, minus the
       share of those successes it loses times its success rate. These runs start the same
       episodes, not with the same policy noise, so each share is that of a fresh attempt; the
       estimate is unbiased but only ranks the entries.
    2. *Confirmation.* The entry with the largest positive estimate (ties: the first listed) and
       the base policy run as many fresh episodes, of ``confirm_seed`` (default ``seed + 1``), as
       the screen took (a number fixed before them, so the sign test is exact); the entry is kept
       only if it wins there with a one-sided sign-test p-value of at most ``alpha``, otherwise
       the most conservative entry is.

    Costs the base policy's episodes plus ``2 x failures`` episodes per entry, then the
    confirmation: where the base policy rarely fails, fewer episodes than :func:`calibrate`'s
    fixed design, which runs every entry on every episode. Stores and returns the record as
    :func:`calibrate` does (``design: "failures"``). Raises ``ValueError`` as :func:`calibrate` does,
    and for fewer than one failure or block.
    """
    for name, value in (("failures", failures), ("block", block), ("min_episodes", min_episodes)):
        check_at_least(name, value, 1)
    check_at_least("max_episodes", max_episodes, min_episodes)
    confirm_seed = seed + 1 if confirm_seed is None else confirm_seed
    _check_calibration(
        world_model_path, grid, rule, alpha, seed, test_seed, confirm_seed, evaluate_kwargs.get("critic")
    )

    def enough(records: list) -> bool:  # checked at block ends only
        return (
            len(records) % block == 0
            and len(records) >= min_episodes
            and sum(not r.success for r in records) >= failures
        )

    conservative = [entry for entry in grid if rule is None or entry.rule == rule][0]
    base = evaluate_checkpoints(
        policy_path,
        world_model_path,
        methods=["base"],
        episodes=max_episodes,
        seed=seed,
        stop_when=enough,
        **evaluate_kwargs,
    )[BASE]
    failed = [r["episode"] for r in base["records"] if not r["success"]]
    solved = [r["episode"] for r in base["records"] if r["success"]][: len(failed)]
    base_rate = base["success_rate"]
    entries = []
    for entry in grid:
        if entry is conservative or not failed or _replays_base_policy(entry, evaluate_kwargs):
            continue
        row = evaluate_checkpoints(
            policy_path,
            world_model_path,
            methods=["dalir"],
            selection=entry,
            seed=seed,
            episodes=len(failed) + len(solved),
            episode_indices=failed + solved,
            **evaluate_kwargs,
        )[DALIR]
        outcome = {r["episode"]: r["success"] for r in row["records"]}
        wins, losses = sum(outcome[e] for e in failed), sum(not outcome[e] for e in solved)
        gain = wins / len(failed) * (1 - base_rate) - (losses / len(solved) * base_rate if solved else 0.0)
        entries.append(
            {
                "name": entry.name,
                "selection": entry.to_dict(),
                "wins": wins,
                "losses": losses,
                "estimated_gain": gain,
                "seconds": row["seconds"],
            }
        )
    ranked = [e for e in family(entries, rule) if e["estimated_gain"] > 0]
    candidate = max(ranked, key=lambda e: e["estimated_gain"]) if ranked else None  # max keeps the first of equals
    chosen, confirmation = conservative, None
    if candidate is not None:  # as many fresh episodes as the screen took: a number its outcomes cannot sway
        confirmation = _confirm(
            policy_path, world_model_path, candidate, base["episodes"], confirm_seed, alpha, **evaluate_kwargs
        )
        chosen = SelectionConfig(**candidate["selection"]) if confirmation["confirmed"] else conservative
    record = {
        "design": "failures",
        "failures": failures,
        "min_episodes": min_episodes,
        "max_episodes": max_episodes,
        "block": block,
        "seed": seed,
        "rule": rule,
        "alpha": alpha,
        "episodes": base["episodes"],
        "base_success_rate": base_rate,
        "failed": failed,
        "solved": solved,
        "entries": entries,
        **({"confirmation": confirmation} if confirmation else {}),
        "chosen": chosen.name,
        "selection": chosen.to_dict(),
    }
    if write:
        store_selection(world_model_path, chosen, record)
    return record


def _replays_base_policy(entry: SelectionConfig, evaluate_kwargs: dict) -> bool:
    """Whether ``entry`` replays the base policy's episodes under the evaluation's reranking settings
    (``reranking=``, ``common_noise=``, ``search=`` of ``evaluate_kwargs``, as :func:`evaluate_checkpoints`
    reads them)."""
    settings = evaluation_reranking(
        evaluate_kwargs.get("reranking"),
        common_noise=evaluate_kwargs.get("common_noise"),
        search=evaluate_kwargs.get("search"),
    )
    return replays_base_policy(entry, settings.common_noise, settings.search)


def _confirm(
    policy_path, world_model_path, entry: dict, episodes: int, seed: int, alpha: float, **evaluate_kwargs
) -> dict:
    """The base policy and ``entry`` (as a calibration records it) on ``episodes`` fresh validation
    episodes of ``seed``: the confirmation's record, ``confirmed`` if the entry wins with a
    one-sided sign-test p-value of at most ``alpha``."""
    rows = evaluate_checkpoints(
        policy_path,
        world_model_path,
        methods=["base", "dalir"],
        selection=SelectionConfig(**entry["selection"]),
        episodes=episodes,
        seed=seed,
        **evaluate_kwargs,
    )
    vs_base = paired_sign_test(*([r["success"] for r in rows[name]["records"]] for name in (BASE, DALIR)))
    return {
        "episodes": episodes,
        "seed": seed,
        "entry": entry["name"],
        "base_success_rate": rows[BASE]["success_rate"],
        "success_rate": rows[DALIR]["success_rate"],
        "vs_base": vs_base,
        "confirmed": p_better(vs_base["base_only"], vs_base["dalir_only"]) <= alpha,
    }


def _check_calibration(world_model_path, grid, rule, alpha, seed, test_seed, confirm_seed, critic=None) -> None:
    """Refuses, before any episode: ``alpha`` outside (0, 1], the test seed as a validation seed, a
    confirmation on the screen's own seed, a ``rule`` no grid entry has, critic rules without a ``critic``,
    and ensemble rules on a world model without a scorer ensemble (``confirm_seed=None``: no confirmation)."""
    if critic is None and any(entry.scorer == "critic" for entry in grid):
        raise ValueError(
            "the grid holds critic rules: pass critic=<critic.pt> (the main job's branched stage trains one)"
        )
    if not 0 < alpha <= 1:
        raise ValueError(f"alpha is a p-value threshold in (0, 1], got {alpha}")
    if test_seed in [seed, *([confirm_seed] if confirm_seed is not None else [])]:
        raise ValueError(f"calibration must not read the test episodes (evaluation seed {test_seed}); use another seed")
    if confirm_seed is not None and confirm_seed == seed:
        raise ValueError(
            f"the confirmation needs fresh validation episodes: confirm_seed must differ from seed ({seed})"
        )
    if rule is not None and not any(entry.rule == rule for entry in grid):
        raise ValueError(f"no entry of the grid has rule {rule!r}: {[entry.name for entry in grid]}")
    checkpoint = load_world_model(world_model_path)
    if checkpoint.ensemble is None and any(entry.scorer == "ensemble" for entry in grid):
        raise ValueError(
            f"{world_model_path} has no scorer ensemble (written before version 0.2.0): retrain the world-model stage"
        )


def choose(entries: list[dict], rule: str | None = None, alpha: float = ALPHA) -> dict:
    """The calibrated entry among ``entries`` (as :func:`calibrate` records them, most
    conservative first), restricted to those of ``rule`` if given: the most successes among the
    first entry and the entries that beat the base policy with a one-sided sign-test p-value of at
    most ``alpha``; ties go to the entry listed first (``alpha=1``: simply the most successes)."""
    eligible = [
        e
        for i, e in enumerate(family(entries, rule))
        if i == 0 or p_better(e["vs_base"]["base_only"], e["vs_base"]["dalir_only"]) <= alpha
    ]
    return max(eligible, key=lambda e: e["success_rate"])  # max keeps the first of equals


def family(entries: list[dict], rule: str | None = None) -> list[dict]:
    """The entries of ``rule`` (all if ``None``), in the grid's order: the first is the most conservative."""
    return [e for e in entries if rule is None or e["selection"]["rule"] == rule]
