"""Are the first draw's winners winners? Each candidate of branched decisions that split, run again from the same
saved state under another draw of the base policy's noise (:mod:`torchrl_dalir.branching.outcome_noise`).

    python examples/paper/outcome_noise.py policy=<run>/checkpoint.pt branched=<collect_branched folder> \\
        json=docs/results/outcome_noise_<run>.json

    # the honest ceiling: every decision (split or not) under the stored draw and three more
    python examples/paper/outcome_noise.py policy=<run>/checkpoint.pt branched=<folder> draws=[1,2,3] \\
        only_split=false json=docs/results/honest_ceiling_<run>.json

Prints how often a first-draw winner wins again against a first-draw loser, the within-decision AUC of the first
draw's outcome as a score of the second's (what a perfect scorer of the chunk could reach at most if the outcome
were all chunk), and the second draw's success rate of the clean candidate, a random one, the first draw's oracle
pick and the second draw's own oracle. Each draw's finished decisions are kept beside the collection
(``<branched>/redraws/``), so a killed run goes on where it stopped and gives the same outcomes. ``draw=0`` re-runs
the collection's own draw (a check: the stored outcomes come back). With several ``draws`` it also prints the
honest ceiling (:func:`~torchrl_dalir.branching.outcome_noise.honest_ceiling`) over the stored draw and the new
ones: the gain of a scorer that knows each chunk's true chance, cross-fitted over draws, beside the clairvoyant
oracle, with the first 2, 4, ... candidates only (how the headroom grows with K) and, where later decisions were
branched too, at each decision index apart.
"""

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchrl_dalir.branching.outcome_noise import (
    honest_ceiling,
    honest_ceiling_by_candidates,
    honest_ceiling_by_decision,
    redraw_outcomes,
    repeatability,
)
from torchrl_dalir.branching.outcomes import DECISION, RESET_SEED, SUCCESS, BranchedOutcomes
from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.config import check_at_least, parse_config
from torchrl_dalir.utils import atomic_write, provenance


@dataclass
class Config:
    policy: str = ""  # a policy checkpoint, .../<task>/<policy>_seed<seed>/checkpoint.pt
    branched: str = ""  # its branched outcomes (a complete collect_branched folder)
    draws: list[int] = field(default_factory=lambda: [1])  # the noise draws after each decision (0: the stored one)
    only_split: bool = True  # only the decisions whose stored candidates split (False: every decision)
    json: str | None = None
    resume: bool = True  # each draw's finished decisions go to <branched>/redraws/; a killed run goes on from there
    progress: bool = True

    def __post_init__(self):
        if not self.draws or len(set(self.draws)) != len(self.draws):
            raise ValueError(f"draws must be distinct noise draws, got {self.draws}")
        for draw in self.draws:
            check_at_least("draws", draw, 0)


def resume_file(cfg: Config, draw: int) -> Path | None:
    """Where draw ``draw``'s finished decisions are kept, beside the collection (None without ``resume``)."""
    return (
        Path(cfg.branched) / "redraws" / f"draw{draw}{'_split' if cfg.only_split else ''}.json" if cfg.resume else None
    )


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    policy = load_policy(cfg.policy)
    outcomes = BranchedOutcomes.load(cfg.branched, policy=policy)
    start = time.perf_counter()
    redrawn = [
        redraw_outcomes(policy, outcomes, d, cfg.only_split, cfg.progress, resume=resume_file(cfg, d))
        for d in cfg.draws
    ]
    stored = redrawn[0]["first_success"]
    measured = repeatability(stored, redrawn[0][SUCCESS])
    print(f"{outcomes}: {json.dumps(measured)}")
    # the stored draw and each new one (draw 0 re-runs the stored draw: a check, not another draw)
    success = torch.stack([stored] + [r[SUCCESS] for d, r in zip(cfg.draws, redrawn) if d != 0], -1)
    ceiling = honest_ceiling(success) if success.shape[-1] > 1 else None
    by_decision = by_candidates = None
    if ceiling is not None:
        print(f"honest ceiling over {ceiling['draws']} draws: {json.dumps(ceiling)}")
        if redrawn[0][DECISION].unique().numel() > 1:  # later decisions branched too: where is the headroom?
            by_decision = honest_ceiling_by_decision(success, redrawn[0][DECISION])
            for d, at in by_decision.items():
                print(f"  decision {d} ({at['decisions']} rows): honest gain {100 * at['honest_gain']:+.1f} points")
        if success.shape[1] > 2:  # fewer candidates from the same states: how the headroom grows with K
            by_candidates = honest_ceiling_by_candidates(success)
            for k, at in by_candidates.items():
                print(
                    f"  K = {k}: honest gain {100 * at['honest_gain']:+.1f}, clairvoyant {100 * at['oracle_gain']:+.1f}"
                )
    payload = {
        **provenance("examples/paper/outcome_noise.py", argv, cfg),
        "task": policy.task,
        "run": Path(cfg.policy).parent.name,
        "seconds": round(time.perf_counter() - start),
        "repeatability": measured,
        "honest_ceiling": ceiling,
        "honest_ceiling_by_decision": by_decision,
        "honest_ceiling_by_candidates": by_candidates,
        "draws": cfg.draws,
        "decisions": [
            {"reset_seed": int(s), "decision": int(d), "first": f.int().tolist(), "second": n.int().T.tolist()}
            for s, d, f, n in zip(
                redrawn[0][RESET_SEED], redrawn[0][DECISION], stored, torch.stack([r[SUCCESS] for r in redrawn], -1)
            )
        ],
    }
    if cfg.json:
        atomic_write(cfg.json, json.dumps(payload, indent=1) + "\n")
    return payload


if __name__ == "__main__":
    main(sys.argv[1:])
