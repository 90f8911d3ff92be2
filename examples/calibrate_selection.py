"""Picks DALI-R's selection rule settings on validation episodes and stores them in the world model.

    python examples/calibrate_selection.py policy_checkpoint=.../checkpoint.pt world_model=.../world_model.pt
    python examples/calibrate_selection.py ... episodes=50 write=false     # only report
    python examples/calibrate_selection.py ... grid=all confirm_episodes=30  # nine settings, the winner confirmed
    # sized by the base policy's failures:
    python examples/calibrate_selection.py ... grid=all design=failures failures=10

The base policy and every rule of the grid (``evaluation.calibration.GRIDS``; by default the
ensemble arg-max alone, as in the main job) run on the same validation episodes (evaluation
seed ``seed``, never the test seed 0). The best setting (of ``rule``, if given) among those that
beat the base policy with a one-sided sign-test p-value of at most ``alpha`` (otherwise the most
conservative setting, the base policy itself) is written into the world-model checkpoint, which
``RerankingActor.from_checkpoints`` and ``examples/evaluate.py`` then use.
``design=failures`` (``evaluation.calibration.calibrate_on_failures``) instead runs the base policy
until it has failed ``failures`` times, screens every rule on those episodes and as many it
solved, and confirms the most promising rule on as many fresh episodes as the screen took: it can
see a gain where the base policy rarely fails. Writes ``<out>/calibration.json`` and prints the table.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import check_choice, config_dict, parse_config
from torchrl_dalir.evaluation.calibration import (
    ALPHA,
    DESIGNS,
    FAILURES,
    GRIDS,
    MAX_EPISODES,
    TEST_SEED,
    VALIDATION_SEED,
    calibrate,
    calibrate_on_failures,
)
from torchrl_dalir.evaluation.compare import COMMON_NOISE, check_evaluation_settings
from torchrl_dalir.reranking import RerankingConfig
from torchrl_dalir.seeds import check_eval_seed
from torchrl_dalir.utils import atomic_write, writable_dir


@dataclass
class Config:
    policy_checkpoint: str = "outputs/pipeline/policies/disassemble/fm_seed0/checkpoint.pt"
    world_model: str = "outputs/pipeline/world_models/fm/disassemble/seed0_frozen+explore_fm_seed0/world_model.pt"
    episodes: int = 30
    seed: int = VALIDATION_SEED  # validation episodes: any evaluation seed but the test seed
    test_seed: int = TEST_SEED  # the evaluation seed of the episodes you report: refused here
    # the entries evaluated: argmax (the base policy and the ensemble arg-max only, the main job's)
    # | all (the margin rule's settings and the other rules; add confirm_episodes=30) | margin
    grid: str = "argmax"
    rule: str | None = None  # choose only among this rule's settings (default: among every entry of the grid)
    # evidence needed to leave the base policy: one-sided sign-test p-value on the validation episodes
    # (1: the best entry)
    alpha: float = ALPHA
    confirm_episodes: int = (
        0  # > 0: the chosen entry must win again on this many fresh validation episodes (evaluation seed seed + 1)
    )
    design: str = (
        "fixed"  # fixed: every entry on `episodes` episodes | failures: sized by the base policy's failures (see above)
    )
    failures: int = FAILURES  # design=failures: the base policy's failures the screen waits for
    max_episodes: int = MAX_EPISODES  # design=failures: the most episodes the screen runs
    write: bool = True  # store the chosen setting in the world-model checkpoint
    device: str = "cpu"
    num_candidates: int = RerankingConfig.num_candidates
    dropout: float = RerankingConfig.dropout
    actor_seed: int = 0
    common_noise: bool = (
        COMMON_NOISE  # DALI-R's clean candidate draws the base policy's own noise (common random numbers)
    )
    out: str | None = None  # default: next to the world model

    def __post_init__(self):
        check_evaluation_settings(self.episodes, self.seed, self.num_candidates, self.dropout)
        check_eval_seed(self.test_seed, "test_seed")
        check_choice("design", self.design, DESIGNS)


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    check_choice("grid", cfg.grid, GRIDS)
    out = writable_dir(cfg.out if cfg.out else Path(cfg.world_model).parent)  # now, not after the episodes
    common = dict(
        grid=GRIDS[cfg.grid],
        rule=cfg.rule,
        alpha=cfg.alpha,
        seed=cfg.seed,
        test_seed=cfg.test_seed,
        write=cfg.write,
        device=cfg.device,
        actor_seed=cfg.actor_seed,
        reranking=RerankingConfig(
            num_candidates=cfg.num_candidates, dropout=cfg.dropout, common_noise=cfg.common_noise
        ),
    )
    if cfg.design == "failures":
        record = calibrate_on_failures(
            cfg.policy_checkpoint, cfg.world_model, failures=cfg.failures, max_episodes=cfg.max_episodes, **common
        )
        print(
            f"\nscreen (evaluation seed {cfg.seed}): the base policy {record['base_success_rate']:.1%} "
            f"over {record['episodes']} episodes, "
            f"{len(record['failed'])} failed; each rule on those and {len(record['solved'])} solved ones"
        )
        for entry in record["entries"]:
            print(
                f"{entry['name']:48s} failures solved {entry['wins']:2d}, successes lost {entry['losses']:2d}, "
                f"estimated gain {entry['estimated_gain']:+.1%}"
            )
    else:
        record = calibrate(
            cfg.policy_checkpoint,
            cfg.world_model,
            episodes=cfg.episodes,
            confirm_episodes=cfg.confirm_episodes,
            **common,
        )
        print(
            f"\nvalidation (evaluation seed {cfg.seed}, {cfg.episodes} episodes): "
            f"base policy {record['base_success_rate']:.1%}"
        )
        for entry in record["entries"]:
            test = entry["vs_base"]
            print(
                f"{entry['name']:48s} {entry['success_rate']:7.1%}   "
                f"only base / only rule {test['base_only']:2d} / {test['dalir_only']:2d}"
            )
    if "confirmation" in record:
        c = record["confirmation"]
        print(
            f"confirmation of {c['entry']} on {c['episodes']} fresh episodes (evaluation seed {c['seed']}): "
            f"{c['success_rate']:.1%} against {c['base_success_rate']:.1%}, "
            f"only base / only rule {c['vs_base']['base_only']} / {c['vs_base']['dalir_only']}: "
            f"{'confirmed' if c['confirmed'] else 'not confirmed, the most conservative entry is kept'}"
        )
    print(f"chosen: {record['chosen']}" + (f" (written to {cfg.world_model})" if cfg.write else ""))
    atomic_write(out / "calibration.json", json.dumps({"config": config_dict(cfg), **record}, indent=1))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
