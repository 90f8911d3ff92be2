"""The main job's evaluation stage: every method on the test episodes, and its report
(``results.md``, ``results.json`` and the imagination diagnostics of held-out trajectories)."""

from __future__ import annotations

import json
from pathlib import Path

from torchrl_dalir.checkpoints import load_policy, load_world_model
from torchrl_dalir.config import config_dict
from torchrl_dalir.data import TrajectoryDataset
from torchrl_dalir.evaluation.compare import (
    ARGMAX,
    BASE,
    DALIR,
    evaluate_checkpoints,
    paired_sign_test,
    pool_decision_summaries,
)
from torchrl_dalir.evaluation.diagnostics import imagination_curves
from torchrl_dalir.evaluation.plots import plot_imagination_diagnostics
from torchrl_dalir.pipeline.config import PipelineConfig
from torchrl_dalir.utils import atomic_write, git_commit


def evaluate_and_report(cfg: PipelineConfig, policy_path: Path, world_model_path: Path) -> None:
    results = cfg.results_dir()
    rows = evaluate_checkpoints(
        policy_path,
        world_model_path,
        episodes=cfg.eval_episodes,
        seed=cfg.eval_seed,
        device=cfg.device,
        reranking=cfg.reranking(),
        actor_seed=cfg.seed,
        methods=cfg.eval_methods,
        critic=cfg.critic(),
    )
    policy = load_policy(policy_path, task=cfg.task)

    # Diagnostics on held-out trajectories: one success and one failure (Fig. 2).
    parts = load_world_model(world_model_path)
    mixed = TrajectoryDataset.load(cfg.collection.mixed_dir(), task=cfg.task)
    held = parts.held_out_trajectories
    labels = mixed.terminal_labels()
    picks = [next((i for i in held if labels[i] == y), None) for y in (1.0, 0.0)]
    curves = [imagination_curves(parts, mixed, i, policy.config.action_steps) for i in picks if i is not None]
    plot = plot_imagination_diagnostics(curves, results / "imagination.png", title=f"{cfg.task}: held-out trajectories")

    metrics = parts.metrics
    base = [r["success"] for r in rows[BASE]["records"]] if BASE in rows else None
    lines = [
        (
            f"# DALI-R on {cfg.task} ({cfg.policy}, seed {cfg.seed}, preset {cfg.preset}, "
            f"scorer target {cfg.world_model.scorer_target})"
        ),
        "",
        (
            f"{cfg.eval_episodes} test episodes (evaluation seed {cfg.eval_seed}); "
            f"DALI-R: {cfg.num_candidates} candidates, point dropout {cfg.dropout}."
        ),
        "",
        "| method | rule | success | only base / only this method | sign-test p |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, row in rows.items():
        test = (
            paired_sign_test(base, [r["success"] for r in row["records"]])
            if base is not None and name != BASE
            else None
        )
        paired = f"{test['base_only']} / {test['dalir_only']} | {test['p_value']:.2f}" if test else " | "
        lines.append(f"| {name} | {row.get('selection', '')} | {row['success_rate']:.1%} | {paired} |")
    lines += [
        "",
        f"Held-out scorer: Brier {metrics['brier']:.4f}, calibration error {metrics['calibration_error']:.4f}. "
        f"Held-out world-model MSE {metrics['wm_mse']:.4f} vs {metrics['no_change_mse']:.4f} for 'no change'.",
    ]
    if "imagined_brier_ensemble" in metrics:
        lines.append(
            "On imagined latents of held-out chunks (target at t + k): "
            f"Brier {metrics['imagined_brier_state_scorer']:.4f} (state scorer) "
            f"vs {metrics['imagined_brier_ensemble']:.4f} (scorer ensemble, member std {metrics['ensemble_std']:.4f})."
        )
    for name in (DALIR, ARGMAX):
        if name in rows and "replays" in rows[name]:
            lines.append(
                f"{name}'s rule ({rows[name]['selection']}) keeps the clean candidate at every decision: "
                f"it is the {rows[name]['replays']}'s episodes, not run again."
            )
        elif name in rows:
            choices = pool_decision_summaries([record["details"] for record in rows[name]["records"]])
            lines.append(
                f"{name}'s choices over {choices['decisions']} decisions: "
                f"the clean candidate kept in {choices['clean_chosen']:.0%}; "
                f"the chosen candidate scored {choices['chosen_margin']:.4f} above the clean one "
                f"(candidate score std {choices['score_spread']:.4f})."
            )
    table = "\n".join(
        [
            *lines,
            f"Diagnostics: {plot.name}",
            "",
        ]
    )
    atomic_write(results / "results.md", table)
    atomic_write(
        results / "results.json",
        json.dumps(
            {
                "config": config_dict(cfg),
                "commit": git_commit(Path(__file__).parent),
                "success": rows,
                "world_model_metrics": metrics,
                "diagnostics": curves,
            },
            indent=1,
        ),
    )
