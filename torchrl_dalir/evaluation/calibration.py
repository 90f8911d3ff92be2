"""Calibrating DALI-R's selection rule on validation episodes, and storing it in the checkpoint.

Every setting of a rule (the margin, the pessimism ``k``, the temperature) is chosen on
*validation* episodes, which have their own evaluation seed, and never on the test episodes
that results report. The base policy and every rule of the grid run on the same validation
episodes; the winner is the entry with the most successes (among those of ``rule`` if one is
named), ties going to the entry listed first. The grids list the most conservative setting first,
``margin=1``, which always executes the clean candidate (with common noise, the default, the
base policy's own chunk: the base policy's episodes exactly), so another setting must solve more
validation episodes than it to be chosen. With 30 validation episodes the best of five settings is partly luck: the test episodes
say what it is worth. The choice is written into the world-model checkpoint, so
:meth:`RerankingActor.from_checkpoints` uses it with no argument.
"""

from __future__ import annotations

from pathlib import Path

from torchrl_dalir.evaluation.compare import BASE, DALIR, evaluate_checkpoints, paired_sign_test
from torchrl_dalir.reranking.selection import SelectionConfig
from torchrl_dalir.training.loop import load_checkpoint, save_checkpoint

TEST_SEED = 0  # the evaluation seed of the episodes that results report
VALIDATION_SEED = 1

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
GRIDS = {"margin": MARGIN_GRID, "all": MARGIN_GRID + COMPARISON_GRID}  # by name, for configurations


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
    **evaluate_kwargs,
) -> dict:
    """Evaluates the base policy and every entry of ``grid`` on ``episodes`` validation episodes
    of evaluation seed ``seed``, picks the best entry (of those whose rule is ``rule``, if given) and, if ``write``,
    stores it in the world-model checkpoint (``selection``, with the whole record under
    ``calibration``). Returns that record: per entry its name, settings, success rate, the
    paired comparison with the base policy, and the chosen entry.

    Raises ``ValueError`` for the test seed ``test_seed``, for a ``rule`` that no grid entry
    has, and for ensemble rules on a world model without a scorer ensemble, before any episode.
    """
    if seed == test_seed:
        raise ValueError(f"calibration must not read the test episodes (evaluation seed {test_seed}); use another seed")
    if rule is not None and not any(entry.rule == rule for entry in grid):
        raise ValueError(f"no entry of the grid has rule {rule!r}: {[entry.name for entry in grid]}")
    state = load_checkpoint(world_model_path, "world_model")  # fails now, not after the base policy's episodes
    if "ensemble_state" not in state and any(entry.scorer == "ensemble" for entry in grid):
        raise ValueError(f"{world_model_path} has no scorer ensemble (written before version 0.2.0): retrain the world-model stage")
    common = dict(episodes=episodes, seed=seed, **evaluate_kwargs)
    base = evaluate_checkpoints(policy_path, world_model_path, methods=["base"], **common)[BASE]
    base_successes = [r["success"] for r in base["records"]]
    entries = []
    for entry in grid:
        row = evaluate_checkpoints(policy_path, world_model_path, methods=["dalir"], selection=entry, **common)[DALIR]
        successes = [r["success"] for r in row["records"]]
        entries.append({"name": entry.name, "selection": entry.to_dict(), "success_rate": row["success_rate"],
                        "vs_base": paired_sign_test(base_successes, successes), "seconds": row["seconds"]})
    family = [e for e in entries if rule is None or e["selection"]["rule"] == rule]
    chosen = max(family, key=lambda e: e["success_rate"])  # max keeps the first of equals
    record = {"episodes": episodes, "seed": seed, "rule": rule, "base_success_rate": base["success_rate"],
              "entries": entries, "chosen": chosen["name"], "selection": chosen["selection"]}
    if write:
        store_selection(world_model_path, SelectionConfig(**chosen["selection"]), record)
    return record


def store_selection(world_model_path: str | Path, selection: SelectionConfig, calibration: dict | None = None) -> None:
    """Writes ``selection`` (and the calibration record) into a world-model checkpoint, atomically."""
    state = load_checkpoint(world_model_path, "world_model")
    if selection.scorer == "ensemble" and "ensemble_state" not in state:
        raise ValueError(f"{world_model_path} has no scorer ensemble for {selection.name}")
    state["selection"], state["calibration"] = selection.to_dict(), calibration
    save_checkpoint(world_model_path, state)
