"""Does more labelled data lift the privileged teacher? Each run's teacher alone and with other runs' decisions.

    python examples/paper/pooled_teacher.py files=[fm_pen_s0,fm_pen_s1,fm_pen_s2,dp_pen_s0] scorers=[teacher] \\
        measured=[fm_pen_s0,fm_pen_s1] json=docs/results/pooled_teacher_pen_a.json   # and the other two: _b

For every benchmark file of one task (``benchmarks/scorer/<name>.pt``), the ladder's teacher rungs
(``SCORERS``' privileged-state scorers, 0/1 and soft targets) out of fold over its own episodes, as
``scorer_benchmark.py`` measures them, then again with every other file's decisions added to each fold's training
(never scored). The teacher reads the simulator's state and the chunk, which mean the same under any policy of the
task; what differs between runs is the base policy that continues after the chunk. Same AUC and gain as the ladder:
within-decision AUC on the run's split decisions, and the offline gain judged by the mean over its draws.
"""

import json
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import torch

from torchrl_dalir.branching.scorer_benchmark import SCORERS, teacher_rows
from torchrl_dalir.config import check_at_least, parse_config
from torchrl_dalir.training.ranking import SOFT_SUCCESS, RankingTrainingConfig, cross_validated_auc
from torchrl_dalir.utils import atomic_write, provenance

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks" / "scorer"


@dataclass
class Config:
    files: list[str] = field(default_factory=list)  # benchmark names (benchmarks/scorer/<name>.pt), one task
    measured: list[str] = field(default_factory=list)  # the files measured (default: all); the others only pool
    scorers: list[str] = field(default_factory=lambda: [n for n, s in SCORERS.items() if "privileged" in s["input"]])
    folds: int = 10
    training: RankingTrainingConfig = field(default_factory=RankingTrainingConfig)
    benchmarks: str = str(BENCHMARKS)
    json: str = ""  # where to write the results (none: print only)

    def __post_init__(self):
        check_at_least("files", len(self.files), 2)
        check_at_least("folds", self.folds, 2)
        unknown = set(self.scorers) - set(SCORERS)
        if unknown:
            raise ValueError(f"unknown scorers {sorted(unknown)}; known: {sorted(SCORERS)}")
        if not set(self.measured) <= set(self.files):
            raise ValueError(f"measured {self.measured} must be among files {self.files}")


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    loaded = {name: teacher_rows(Path(cfg.benchmarks) / f"{name}.pt") for name in cfg.files}
    tasks = {info["task"] for _, info in loaded.values()}
    if len(tasks) != 1:
        raise ValueError(f"pool runs of one task: the files hold {sorted(tasks)}")
    results = {}
    for name in cfg.measured or cfg.files:
        rows, info = loaded[name]
        others = torch.cat([other for key, (other, _) in loaded.items() if key != name])
        policy = SimpleNamespace(**info["sizes"])
        results[name] = {"decisions": len(rows), "pooled_decisions": len(rows) + len(others)}
        for scorer in cfg.scorers:
            training = replace(cfg.training, **SCORERS[scorer])
            for label, pool in (("alone", None), ("pooled", others)):
                cv = cross_validated_auc(rows, policy, training, cfg.folds, rows[SOFT_SUCCESS], pool=pool)
                gain = cv["pick_success"] - cv["clean_success"]
                results[name][f"{scorer}_{label}"] = {"auc": cv["auc"], "gain": gain}
                print(f"{name} {scorer} {label}: AUC {cv['auc']:.3f}, gain {100 * gain:+.1f} points", flush=True)
    out = {**provenance("examples/paper/pooled_teacher.py", argv, cfg), "task": tasks.pop(), "runs": results}
    if cfg.json:
        atomic_write(Path(cfg.json), json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
