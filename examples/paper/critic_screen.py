"""Screen a chunk critic trained on branched outcomes: the base policy against the critic choosing among
point-dropout candidates at each episode's first decisions, on the same episodes (validation by default).

    python examples/paper/critic_screen.py policy=<run>/checkpoint.pt branched=<collect_branched folder> \\
        json=docs/results/critic_screen_<run>.json
    python examples/paper/critic_screen.py ... seed=0 test=true   # test episodes: only for a screen that passed

1. The critic variant: each of ``variants`` (``outcome``: the terminal-label loss alone; ``ranking``: the
   listwise loss beside it) is measured by its out-of-fold within-decision AUC on the branched decisions
   (data seeds only, :func:`~torchrl_dalir.training.ranking.cross_validated_auc`); the higher one is kept.
2. That variant is trained on every branched decision and saved as ``<out>/critic.pt``.
3. The base policy and :class:`~torchrl_dalir.reranking.RerankingActor` with the critic alone (no world
   model; the candidates the branched data were made with; ``decisions`` first decisions reranked, then the
   base policy; common noise) run the same ``episodes`` episodes of evaluation seed ``seed``
   (:func:`~torchrl_dalir.evaluation.compare.evaluate_checkpoints`). The paired sign test and every
   episode's outcome go to ``json``.

With ``student=<scorer benchmark file>`` instead of ``branched=``, the critic is the point-cloud student distilled
from the privileged teacher (:func:`~torchrl_dalir.training.distillation.train_student`) on that benchmark's
branched decisions and its distillation file (``benchmarks/scorer/distill/<name>.pt``), trained on all of them;
its out-of-fold measure is the scorer benchmark's (``docs/results/scorer_benchmark.json``), and the candidates are
the benchmark's (8 point-dropout candidates, p = 0.2, the clean one first):

    python examples/paper/critic_screen.py policy=<run>/checkpoint.pt \
        student=benchmarks/scorer/fm_pick_place_wall_s0.pt json=docs/results/student_screen_<run>.json

The rule that decides whether a screen passes is written down before it runs
(``docs/results/critic_screen_prereg.json``, ``student_screen_prereg.json``); test episodes (``seed=0``) need
``test=true``.
"""

import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from torchrl_dalir.branching.outcomes import SUCCESS, BranchedOutcomes
from torchrl_dalir.branching.scorer_benchmark import all_draws, load_benchmark, load_distillation
from torchrl_dalir.checkpoints import load_policy, save_chunk_critic
from torchrl_dalir.config import check_at_least, check_choice, parse_config
from torchrl_dalir.evaluation.calibration import TEST_SEED
from torchrl_dalir.evaluation.compare import (
    BASE,
    DALIR,
    evaluate_checkpoints,
    paired_sign_test,
    pool_decision_summaries,
)
from torchrl_dalir.reranking import RerankingConfig
from torchrl_dalir.training.distillation import DistillationConfig, train_student
from torchrl_dalir.training.ranking import CRITIC_VARIANTS, SOFT_SUCCESS, RankingTrainingConfig, fit_critic
from torchrl_dalir.utils import atomic_write, provenance


@dataclass
class Config:
    policy: str = ""  # a policy checkpoint, .../<task>/<policy>_seed<seed>/checkpoint.pt
    branched: str = ""  # its branched outcomes (a complete collect_branched folder)
    student: str = ""  # or a scorer benchmark file: screen the student distilled on it and its distillation file
    distillation: DistillationConfig = field(default_factory=DistillationConfig)
    variants: list[str] = field(default_factory=lambda: ["outcome", "ranking"])
    folds: int = 10  # out-of-fold groups of episodes for choosing the variant
    training: RankingTrainingConfig = field(default_factory=RankingTrainingConfig)
    decisions: int = 1  # rerank each episode's first decisions (the branched data's), then the base policy acts
    episodes: int = 50
    seed: int = 1  # evaluation seed: 1 holds the validation episodes, 0 the test episodes
    test: bool = False  # allow seed 0, after a screen passed by the committed rule
    actor_seed: int = 0
    out: str = "outputs/critic_screen"
    json: str | None = None
    progress: bool = True

    def __post_init__(self):
        if bool(self.branched) == bool(self.student):
            raise ValueError("pass branched= (a chunk critic) or student= (a scorer benchmark file), not both")
        for variant in self.variants:
            check_choice("variants entry", variant, CRITIC_VARIANTS)
        check_at_least("episodes", self.episodes, 1)
        check_at_least("decisions", self.decisions, 1)
        if self.seed == TEST_SEED and not self.test:
            raise ValueError(f"seed={TEST_SEED} holds the test episodes: screen on seed=1; test=true once it passed")


def chunk_critic(cfg: Config, policy) -> tuple:
    """The chunk critic of ``cfg.branched`` (the variant with the better out-of-fold AUC), its reranking settings
    (the branched data's candidates) and what the record keeps of it."""
    outcomes = BranchedOutcomes.load(cfg.branched, policy=policy)
    critic, metrics = fit_critic(outcomes, policy, cfg.training, tuple(cfg.variants), cfg.folds)
    variant, aucs = metrics["variant"], metrics["out_of_fold"]
    print(
        f"[critic] {outcomes}: out-of-fold AUC { ({v: round(a['auc'], 3) for v, a in aucs.items()}) }; kept {variant}"
    )
    meta = outcomes.meta
    reranking = RerankingConfig.with_generator(
        meta.candidates, meta.setting, num_candidates=meta.num_candidates, common_noise=True, decisions=cfg.decisions
    )
    branched = {"rows": len(outcomes), "split_decisions": int(outcomes.split_decisions().sum()), **asdict(meta)}
    branched.pop("done_episodes")
    record = {"variant": variant, "out_of_fold": aucs, "train_auc": metrics["train_auc"]}
    return critic, metrics, reranking, {"branched": branched, "critic": record}


def distilled_student(cfg: Config, policy) -> tuple:
    """The student distilled on every decision of the benchmark ``cfg.student`` and its distillation file, the
    benchmark's candidates, and what the record keeps of it."""
    rows, info = load_benchmark(cfg.student)
    if info["task"] != policy.task:
        raise ValueError(f"{cfg.student} is a {info['task']} benchmark; the policy's task is {policy.task}")
    states, distill = load_distillation(Path(cfg.student).parent / "distill" / Path(cfg.student).name)
    chance = all_draws(rows).float().mean(-1)
    student, metrics = train_student(
        rows.set(SOFT_SUCCESS, chance), policy, cfg.distillation, None, states, distill["encoders"]
    )
    print(f"[student] {len(rows)} branched decisions, {len(states)} distillation states")
    reranking = RerankingConfig(num_candidates=rows[SUCCESS].shape[1], common_noise=True, decisions=cfg.decisions)
    digests = {"benchmark": info["policy_digest"], "distillation": distill["policy_digest"]}
    return student, metrics, reranking, {"student": {"benchmark": cfg.student, "policy_digests": digests, **metrics}}


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    policy = load_policy(cfg.policy)
    out = Path(cfg.out) / policy.task / Path(cfg.policy).parent.name
    out.mkdir(parents=True, exist_ok=True)

    start = time.perf_counter()
    critic, metrics, reranking, record = (distilled_student if cfg.student else chunk_critic)(cfg, policy)
    save_chunk_critic(out / "critic.pt", critic, policy, metrics)
    training_seconds = time.perf_counter() - start

    rows = evaluate_checkpoints(
        cfg.policy,
        critic=critic,
        methods=["base", "dalir"],
        episodes=cfg.episodes,
        seed=cfg.seed,
        reranking=reranking,
        actor_seed=cfg.actor_seed,
        progress=cfg.progress,
    )
    rows = {"base policy": rows[BASE], "critic": rows[DALIR]}
    base, chosen = ([r["success"] for r in rows[m]["records"]] for m in ("base policy", "critic"))
    paired = paired_sign_test(base, chosen)
    choices = pool_decision_summaries([r["details"] for r in rows["critic"]["records"]])
    print(
        f"[screen] critic won {paired['dalir_only']}, lost {paired['base_only']} (p = {paired['p_value']:.3f}); "
        f"kept the clean candidate at {choices['clean_chosen']:.0%} of {choices['decisions']} reranked decisions"
    )
    payload = {
        **provenance("examples/paper/critic_screen.py", argv, cfg),
        "task": policy.task,
        "run": Path(cfg.policy).parent.name,
        **record,
        "critic_seconds": round(training_seconds, 1),
        "reranking": {
            "num_candidates": reranking.num_candidates,
            "candidates": reranking.candidates,
            "setting": reranking.generator_setting,
            "decisions": reranking.decisions,
        },
        "paired": paired,
        "critic_choices": choices,
        "methods": rows,
    }
    if cfg.json:
        atomic_write(cfg.json, json.dumps(payload, indent=1) + "\n")
    return payload


if __name__ == "__main__":
    main(sys.argv[1:])
