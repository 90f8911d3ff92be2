"""Branched outcomes on data seeds, then a scorer that ranks within a state, measured by its
within-decision AUC on held-out decisions that split (before any test episode).

    python examples/paper/branched_ranking.py policy=outputs/pipeline/policies/pick-place-wall/fm_seed0/checkpoint.pt
    python examples/paper/branched_ranking.py policy=... episodes=30 num_candidates=8 \\
        json=docs/results/branched_ranking.json

Collects (or resumes) the branched outcomes of ``policy`` under ``<out>/<task>/<run>/`` with
:func:`~torchrl_dalir.branching.outcomes.collect_branched`, then trains each scorer variant of
``variants`` on the first episodes and measures it on the last ones
(:func:`~torchrl_dalir.training.ranking.train_ranking_scorer`): ``ranking`` (listwise loss beside
the terminal-label loss) and ``outcome`` (the terminal-label loss alone), both on the current
state and the chunk, on a held-out share of the episodes and out of fold (every episode scored by a
scorer trained on the others), beside two scores that need no training. With ``world_model=`` (the
policy's), ``ranking_imagined`` and ``outcome_imagined`` read the imagined latent instead, as the paper's
scorer does, and the world model's own scorers are measured too. With ``mixed=`` (the policy's mixed
data), the no-simulator route: chunk critics trained on the mixed data alone (terminal labels, with and
without a distance hinge against noise-perturbed chunks or the policy's own candidates,
:class:`~torchrl_dalir.objectives.DistanceHingeLoss`), measured on every branched decision that splits.
Prints a markdown table; ``json`` writes it with the data's counts.

    python examples/paper/branched_ranking.py policy=... world_model=<run>/world_model.pt \
        mixed=<out>/data/<task>/mixed_fm_seed0 variants=[ranking,outcome,ranking_imagined,outcome_imagined]
"""

import json
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from torchrl_dalir import RerankingActor
from torchrl_dalir.branching.candidate_outcomes import within_decision_auc
from torchrl_dalir.branching.outcomes import RESET_SEED, collect_branched
from torchrl_dalir.checkpoints import load_policy, load_world_model
from torchrl_dalir.config import check_choice, parse_config
from torchrl_dalir.data.storage import TrajectoryDataset
from torchrl_dalir.modules.config import executed_slice
from torchrl_dalir.reranking import RerankingConfig, SelectionConfig
from torchrl_dalir.training.ranking import (
    MixedCriticConfig,
    RankingTrainingConfig,
    critic_auc,
    cross_validated_auc,
    train_mixed_critic,
    train_ranking_scorer,
)
from torchrl_dalir.utils import atomic_write, provenance

VARIANTS = {
    "ranking": {"ranking": True},
    "outcome": {"ranking": False},
    "ranking_imagined": {"ranking": True, "input": "imagined"},  # these two need world_model=
    "outcome_imagined": {"ranking": False, "input": "imagined"},
}
# The no-simulator route (mixed=): chunk critics of the mixed data, never trained on a branched decision.
MIXED_VARIANTS = {
    "mixed_labels": {"hinge_weight": 0.0},
    "mixed_noise_hinge": {"negatives": "noise"},
    "mixed_policy_hinge": {"negatives": "policy"},
}


def reference_aucs(outcomes, policy) -> dict:
    """Within-decision AUCs of two scores that need no training, on the decisions that split: the clean
    candidate first (1 for candidate 0, 0 for the others), and nearness to the clean candidate's actions."""
    rows = outcomes.rows
    executed = rows["action_chunk"][:, :, executed_slice(policy.obs_steps, policy.action_steps)]
    distance = (executed - executed[:, :1]).flatten(2).norm(dim=-1)
    clean = torch.zeros_like(distance)
    clean[:, 0] = 1
    success = rows["success"].tolist()
    return {
        "clean_first": within_decision_auc(clean.tolist(), success),
        "near_clean": within_decision_auc((-distance).tolist(), success),
    }


def paper_scorer_aucs(outcomes, policy, world_model: str) -> dict:
    """Within-decision AUCs of the world model's own scorers on the imagined latents of the candidates
    (the paper's state scorer and the scorer ensemble's mean), on the decisions that split."""
    rows, aucs = outcomes.rows, {}
    for scorer in ("state", "ensemble"):
        actor = RerankingActor.on_policy(policy, world_model, selection=SelectionConfig(scorer=scorer))
        scores = actor.score(rows["point_cloud"], rows["agent_pos"], rows["action_chunk"])
        aucs[f"paper_{scorer}_scorer"] = within_decision_auc(scores.tolist(), rows["success"].tolist())
    return aucs


@dataclass
class Config:
    policy: str = ""  # a policy checkpoint, .../<task>/<policy>_seed<seed>/checkpoint.pt
    generator: str = "dropout"  # or clean (re-sampling the policy's noise) or noise (Gaussian point noise)
    dropout: float = RerankingConfig.dropout
    noise_std: float = RerankingConfig.noise_std
    num_candidates: int = 8
    episodes: int = 30
    stride: int = 2
    decisions: int = 0  # only the decisions before this index (0: all)
    data_seed: int = 500_000  # the episodes' reset seeds start here (data seeds, never evaluation seeds)
    variants: list[str] = field(default_factory=lambda: ["ranking", "outcome"])
    training: RankingTrainingConfig = field(default_factory=RankingTrainingConfig)
    folds: int = 0  # out-of-fold groups of episodes (0: one per episode)
    learning_curve: list[int] = field(default_factory=list)  # also the out-of-fold AUCs on the first n episodes
    world_model: str | None = None  # the policy's world model: the imagined-latent variants and the paper's scorer
    mixed: str | None = None  # the policy's mixed data: the no-simulator critics (MIXED_VARIANTS)
    mixed_training: MixedCriticConfig = field(default_factory=MixedCriticConfig)
    out: str = "outputs/branched"
    json: str | None = None
    progress: bool = True

    def __post_init__(self):
        if not Path(self.policy).is_file():
            raise FileNotFoundError(f"no policy checkpoint at {self.policy!r}: pass policy=<checkpoint.pt>")
        self.reranking()  # an unknown generator fails here
        for variant in self.variants:
            check_choice("variants entry", variant, VARIANTS)
            if VARIANTS[variant].get("input") == "imagined" and self.world_model is None:
                raise ValueError(f"variant {variant} reads imagined latents: pass world_model=<world_model.pt>")

    def reranking(self) -> RerankingConfig:
        return RerankingConfig(self.num_candidates, self.generator, self.dropout, self.noise_std)


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    policy = load_policy(cfg.policy)
    run = Path(cfg.policy).parent.name
    start = time.perf_counter()
    outcomes = collect_branched(
        policy,
        Path(cfg.out) / policy.task / run / cfg.generator,
        cfg.reranking(),
        episodes=cfg.episodes,
        stride=cfg.stride,
        decisions=cfg.decisions,
        seed=cfg.data_seed,
        progress=cfg.progress,
    )
    collection_seconds = time.perf_counter() - start
    split = outcomes.split_decisions()
    imagination = {}
    if cfg.world_model is not None:
        parts = load_world_model(cfg.world_model, policy=policy)
        imagination = {"encoder": parts.encoder, "world_model": parts.world_model}
    results = {}
    for variant in cfg.variants:
        training = replace(cfg.training, **VARIANTS[variant])
        _, metrics = train_ranking_scorer(outcomes, policy, training, **imagination)
        metrics.pop("held_out_logits")
        cv = cross_validated_auc(outcomes, policy, training, folds=cfg.folds, **imagination)
        results[variant] = {**metrics, "cross_validated": cv}
    print(f"{outcomes}: {int(split.sum())} of {len(outcomes)} decisions split; collected in {collection_seconds:.0f} s")
    curve = {}  # the out-of-fold AUC on the first n episodes: does more branched data help?
    for n in cfg.learning_curve:
        first = outcomes.rows[outcomes.rows[RESET_SEED] < cfg.data_seed + n].to_tensordict()
        curve[n] = {
            variant: cross_validated_auc(
                first, policy, replace(cfg.training, **VARIANTS[variant]), folds=cfg.folds, **imagination
            )
            for variant in cfg.variants
        }
        print(
            f"first {n} episodes: "
            + ", ".join(f"{v} {m['auc']:.3f} ({m['split_decisions']})" for v, m in curve[n].items())
        )
    baselines = reference_aucs(outcomes, policy)
    if cfg.world_model is not None:
        baselines.update(paper_scorer_aucs(outcomes, policy, cfg.world_model))
    mixed = {}
    if cfg.mixed is not None:
        dataset = TrajectoryDataset.load(cfg.mixed, task=policy.task)
        for variant, settings in MIXED_VARIANTS.items():
            critic, metrics = train_mixed_critic(dataset, policy, replace(cfg.mixed_training, **settings))
            mixed[variant] = {**metrics, **critic_auc(critic, outcomes, policy)}
            print(f"no-simulator critic {variant}: within-decision AUC {mixed[variant]['auc']:.3f}")
    print(f"references on the split decisions: {baselines}")
    print(
        "| variant | input | train AUC (split) | held-out AUC (split) | out-of-fold AUC, a fold per episode (split) |\n"
        "| --- | --- | --- | --- | --- |"
    )
    for variant, m in results.items():
        cv = m["cross_validated"]
        print(
            f"| {variant} | {m['config']['input']} | {m['train_auc']:.3f} ({m['train_split_decisions']}) | "
            f"{m['held_out_auc']:.3f} ({m['held_out_split_decisions']}) | {cv['auc']:.3f} ({cv['split_decisions']}) |"
        )
    payload = {
        **provenance("examples/paper/branched_ranking.py", argv, cfg),
        "task": policy.task,
        "run": run,
        "decisions": len(outcomes),
        "split_decisions": int(split.sum()),
        "candidate_success_rate": float(outcomes.rows["success"].float().mean()),
        "collection_seconds_this_attempt": round(collection_seconds),
        "reference_aucs": baselines,
        "variants": results,
        "learning_curve": curve,
        "mixed_data_critics": mixed,
    }
    if cfg.json:
        atomic_write(cfg.json, json.dumps(payload, indent=1) + "\n")
    return payload


if __name__ == "__main__":
    main(sys.argv[1:])
