"""Are the first draw's winners winners? Each candidate of branched decisions that split, run again from the same
saved state under another draw of the base policy's noise (:mod:`torchrl_dalir.evaluation.outcome_noise`).

    python examples/paper/outcome_noise.py policy=<run>/checkpoint.pt branched=<collect_branched folder> \\
        json=docs/results/outcome_noise_<run>.json

Prints how often a first-draw winner wins again against a first-draw loser, the within-decision AUC of the
first draw's outcome as a score of the second's (what a perfect scorer of the chunk could reach at most if the
outcome were all chunk), and the second draw's success rate of the clean candidate, a random one, the first
draw's oracle pick and the second draw's own oracle. ``draw=0`` re-runs the collection's own draw (a check:
the stored outcomes come back).
"""

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.config import check_at_least, parse_config
from torchrl_dalir.data.branched import BranchedOutcomes
from torchrl_dalir.evaluation.outcome_noise import redraw_outcomes, repeatability
from torchrl_dalir.utils import atomic_write, provenance


@dataclass
class Config:
    policy: str = ""  # a policy checkpoint, .../<task>/<policy>_seed<seed>/checkpoint.pt
    branched: str = ""  # its branched outcomes (a complete collect_branched folder)
    draw: int = 1  # the noise draw after each decision (0: the collection's own)
    json: str | None = None
    progress: bool = True

    def __post_init__(self):
        check_at_least("draw", self.draw, 0)


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    policy = load_policy(cfg.policy)
    outcomes = BranchedOutcomes.load(cfg.branched, policy=policy)
    start = time.perf_counter()
    redrawn = redraw_outcomes(policy, outcomes, cfg.draw, progress=cfg.progress)
    measured = repeatability(redrawn["first_success"], redrawn["success"])
    print(f"{outcomes}: {json.dumps(measured)}")
    payload = {
        **provenance("examples/paper/outcome_noise.py", argv, cfg),
        "task": policy.task,
        "run": Path(cfg.policy).parent.name,
        "seconds": round(time.perf_counter() - start),
        "repeatability": measured,
        "decisions": [
            {"reset_seed": int(s), "decision": int(d), "first": f.int().tolist(), "second": n.int().tolist()}
            for s, d, f, n in zip(
                redrawn["reset_seed"], redrawn["decision"], redrawn["first_success"], redrawn["success"]
            )
        ],
    }
    if cfg.json:
        atomic_write(cfg.json, json.dumps(payload, indent=1) + "\n")
    return payload


if __name__ == "__main__":
    main(sys.argv[1:])
