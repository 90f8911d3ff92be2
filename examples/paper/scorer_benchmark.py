"""The scorer benchmark: every scorer's out-of-fold AUC and offline gain beside the honest ceiling, on a laptop CPU.

    python examples/paper/scorer_benchmark.py                      # every benchmarks/scorer/*.pt: minutes
    python examples/paper/scorer_benchmark.py json=docs/results/scorer_benchmark.json

    # a benchmark file from a policy's branched first decisions and their redraws (needs the simulator once)
    python examples/paper/scorer_benchmark.py build=benchmarks/scorer/fm_pick_place_wall_s0.pt \\
        policy=<run>/checkpoint.pt branched=<collect_branched folder> redraws=<outcome_noise.py json>
    # its distillation file: first decisions of fresh data seeds with the policy's candidates (no continuation;
    # decisions=4: each episode's first 4, for a benchmark branched at as many)
    python examples/paper/scorer_benchmark.py distill=benchmarks/scorer/distill/fm_pick_place_wall_s0.pt \\
        policy=<run>/checkpoint.pt states=1000 seed=600000

The file format and the measures are :mod:`torchrl_dalir.branching.scorer_benchmark`. The ladder's rungs: the
honest ceiling (a scorer that knows each chunk's true chance, cross-fitted over draws), a chunk's first outcome
as a score of its next, the clean candidate, the point-cloud chunk critic (the frozen policy's condition; 0/1 or
soft targets), the privileged teacher (the simulator's low-dimensional state; training-time only) and the student
distilled from it (a point-cloud critic with encoders of its own, where ``distill/<name>.pt`` exists). Scorers
whose inputs the files do not hold are listed as skipped, with the reason.
"""

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchrl_dalir.branching.outcome_noise import privileged_states
from torchrl_dalir.branching.outcomes import DECISION, RESET_SEED, BranchedOutcomes
from torchrl_dalir.branching.scorer_benchmark import (
    SCORERS,
    benchmark_rows,
    distillation_contents,
    distillation_states,
    load_benchmark,
    load_distillation,
    save_benchmark,
    scorer_ladder,
)
from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.config import check_at_least, parse_config
from torchrl_dalir.reranking.config import RerankingConfig
from torchrl_dalir.training.distillation import DistillationConfig
from torchrl_dalir.training.ranking import RankingTrainingConfig
from torchrl_dalir.utils import atomic_write, provenance

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks" / "scorer"
# The rungs the committed files cannot measure yet, and why.
SKIPPED = {"paper_scorer": "needs the run's world-model checkpoint, which the repository does not hold"}
NO_DISTILLATION = "no distillation file (distill/<name>.pt) for this benchmark"


@dataclass
class Config:
    files: list[str] = field(default_factory=list)  # benchmark files (default: every benchmarks/scorer/*.pt)
    scorers: list[str] = field(default_factory=lambda: list(SCORERS))
    folds: int = 10
    training: RankingTrainingConfig = field(default_factory=RankingTrainingConfig)
    student: bool = True  # the distilled student, where a distillation file exists (the slowest rung)
    distillation: DistillationConfig = field(default_factory=DistillationConfig)
    json: str | None = None
    # build a benchmark file instead (the path to write), from:
    build: str | None = None
    policy: str = ""  # the policy checkpoint
    branched: str = ""  # its branched first decisions (a complete collect_branched folder)
    redraws: str = ""  # outcome_noise.py's JSON of every decision (only_split=false) under further draws
    # or a distillation file (the path to write), from policy= (the benchmark's, or one retrained by the same
    # command: the ladder records both digests) and:
    distill: str | None = None
    states: int = 1000  # base-policy episodes of data seeds seed, seed + 1, ... (none shared with the benchmark's)
    seed: int = 600_000
    num_candidates: int = 8  # as many as the benchmark's decisions hold
    decisions: int = 1  # each episode's first decisions (the benchmark's branched decisions=)

    def __post_init__(self):
        unknown = set(self.scorers) - set(SCORERS)
        if unknown:
            raise ValueError(f"unknown scorers {sorted(unknown)}; the scorers are {list(SCORERS)}")
        if self.build and not (self.policy and self.branched and self.redraws):
            raise ValueError("build= needs policy=, branched= and redraws= (outcome_noise.py only_split=false json)")
        check_at_least("decisions", self.decisions, 1)
        if self.distill and not self.policy:
            raise ValueError("distill= needs policy= (the benchmark's policy checkpoint)")


def build(cfg: Config) -> dict:
    """Writes one benchmark file: the branched rows, their redraws and the replayed privileged states."""
    policy = load_policy(cfg.policy)
    rows = BranchedOutcomes.load(cfg.branched, policy=policy).rows.to_tensordict()
    measured = json.loads(Path(cfg.redraws).read_text())
    redrawn = {(d["reset_seed"], d["decision"]): d["second"] for d in measured["decisions"]}
    decisions = list(zip(rows[RESET_SEED].tolist(), rows[DECISION].tolist()))
    missing = [key for key in decisions if key not in redrawn]
    if missing:
        raise ValueError(
            f"{cfg.redraws} lacks {len(missing)} decisions of {cfg.branched} (e.g. {missing[0]}): "
            "run outcome_noise.py with only_split=false"
        )
    # outcome_noise.py stores [draws][K] per decision; a draw 0 re-run is the stored outcome, not a draw
    new = [i for i, d in enumerate(measured["draws"]) if d != 0]
    redraws = torch.tensor([[redrawn[key][i] for i in new] for key in decisions]).transpose(1, 2)
    contents = benchmark_rows(policy, rows, redraws, privileged_states(policy, rows, progress=False))
    contents["source"] = {"policy": cfg.policy, "branched": cfg.branched, "redraws": cfg.redraws}
    save_benchmark(cfg.build, contents)
    print(f"{cfg.build}: {len(rows)} decisions x {redraws.shape[1]} candidates, {redraws.shape[2] + 1} draws")
    return contents


def build_distillation(cfg: Config) -> dict:
    """Writes one distillation file: fresh decisions with the policy's candidates, and its encoders."""
    policy = load_policy(cfg.policy)
    reranking = RerankingConfig(num_candidates=cfg.num_candidates)
    states = distillation_states(policy, cfg.seed, cfg.states, reranking, decisions=cfg.decisions)
    contents = distillation_contents(policy, states)
    contents["source"] = {"policy": cfg.policy, "seed": cfg.seed, "decisions": cfg.decisions}
    save_benchmark(cfg.distill, contents, compress=True)
    print(f"{cfg.distill}: {len(states)} decision states x {cfg.num_candidates} candidates")
    return contents


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    if cfg.build:
        build(cfg)
        return {}
    if cfg.distill:
        build_distillation(cfg)
        return {}
    files = [Path(f) for f in cfg.files] or sorted(BENCHMARKS.glob("*.pt"))
    if not files:
        raise FileNotFoundError(f"no benchmark files in {BENCHMARKS}: pass files=[...] or build one (build=...)")
    results, skipped = {}, dict(SKIPPED)
    for path in files:
        start = time.perf_counter()
        rows, info = load_benchmark(path)
        distill = path.parent / "distill" / path.name
        if cfg.student and not distill.is_file():
            skipped[f"student ({path.stem})"] = NO_DISTILLATION
        distill = load_distillation(distill) if cfg.student and distill.is_file() else None
        if distill is not None and distill[1]["task"] != info["task"]:
            raise ValueError(f"{path} is {info['task']}, its distillation file {distill[1]['task']}")
        ladder = scorer_ladder(
            rows,
            info["sizes"],
            cfg.training,
            cfg.folds,
            {s: SCORERS[s] for s in cfg.scorers},
            distill,
            cfg.distillation,
        )
        results[path.stem] = {
            "task": info["task"],
            "policy_digest": info["policy_digest"],
            **({"distillation_policy_digest": distill[1]["policy_digest"]} if distill is not None else {}),
            **ladder,
            "seconds": round(time.perf_counter() - start),
        }
        print(table(path.stem, results[path.stem]), flush=True)
    print("skipped: " + "; ".join(f"{name}: {why}" for name, why in skipped.items()))
    payload = {**provenance("examples/paper/scorer_benchmark.py", argv, cfg), "benchmarks": results, "skipped": skipped}
    if cfg.json:
        atomic_write(cfg.json, json.dumps(payload, indent=1) + "\n")
    return payload


def table(name: str, ladder: dict) -> str:
    """One benchmark's ladder as markdown: AUC on the split decisions, gain over all decisions (points)."""
    ceiling = ladder["honest_ceiling"]
    lines = [
        f"{name} ({ladder['decisions']} decisions, {ladder['split_decisions']} split, {ladder['draws']} draws)",
        "| scorer | within-decision AUC (split) | offline gain (points) |",
        "| --- | --- | --- |",
        f"| honest ceiling (true chance, cross-fitted) | {ceiling['true_chance_auc']:.3f} | "
        f"{100 * ceiling['honest_gain']:+.1f} |",
        f"| clairvoyant oracle | - | {100 * ceiling['oracle_gain']:+.1f} |",
        f"| first outcome | {ladder['first_outcome']['auc']:.3f} | - |",
    ]
    for rung in ("clean", *SCORERS, "student"):
        if rung in ladder:
            lines.append(f"| {rung} | {ladder[rung]['auc']:.3f} | {100 * ladder[rung]['gain']:+.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main(sys.argv[1:])
