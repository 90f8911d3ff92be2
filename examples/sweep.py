"""The main job over tasks and seeds, then the summary table: the benchmark protocol in one command.

    python examples/sweep.py out=outputs/pipeline                       # 4 MetaWorld tasks x 3 seeds, FM
    python examples/sweep.py tasks=[shelf-place] seeds=[1,2] policy=dp jobs=1 threads=2

Every run is its own ``examples/train_dp3_wm.py`` process, so a run that crashes does not stop
the others, and a stopped sweep resumes where it was (finished stages are skipped). Runs go
seed-major (every task's seed 0 first) ``jobs`` at a time with ``threads`` threads each; on a
2-core CPU two one-thread runs side by side use the cores better than one two-thread run.
Each run's output goes to ``<out>/logs/``; exit codes and wall times to ``<out>/sweep.json``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.pipeline import PRESETS, PipelineConfig
from torchrl_dalir.utils import atomic_write, run_logged

EXAMPLES = Path(__file__).resolve().parent


@dataclass
class Config:
    tasks: list[str] = field(default_factory=lambda: ["disassemble", "shelf-place", "stick-pull", "pick-place-wall"])
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    policy: str = "fm"
    preset: str = "cpu"
    out: str = "outputs/pipeline"
    jobs: int = 2  # runs side by side
    threads: int = 1  # torch threads per run
    overrides: list[str] = field(default_factory=list)  # passed to every run, e.g. [eval_episodes=100]


def run_arguments(cfg: Config, task: str, seed: int) -> list[str]:
    return [f"task={task}", f"seed={seed}", f"policy={cfg.policy}", f"preset={cfg.preset}", f"out={cfg.out}", *cfg.overrides]


def run_one(cfg: Config, task: str, seed: int) -> dict:
    name = f"{task}_{cfg.policy}_seed{seed}"
    log = Path(cfg.out) / "logs" / f"{name}.log"
    code, seconds = run_logged([sys.executable, str(EXAMPLES / "train_dp3_wm.py"), *run_arguments(cfg, task, seed)], log, cfg.threads)
    print(f"[sweep] {name}: {'ok' if code == 0 else f'FAILED (exit {code}), see {log}'} in {seconds / 60:.1f} min", flush=True)
    return {"task": task, "seed": seed, "policy": cfg.policy, "exit_code": code, "seconds": round(seconds, 1), "log": str(log)}


def main(argv: list[str]) -> None:
    cfg = parse_config(Config, argv)
    runs = [(task, seed) for seed in cfg.seeds for task in cfg.tasks]
    for run in runs:  # a bad task, policy, preset or override fails now, not an hour into the sweep
        parse_config(PipelineConfig, run_arguments(cfg, *run), PRESETS)
    with ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
        records = list(pool.map(lambda run: run_one(cfg, *run), runs))
    atomic_write(Path(cfg.out) / "sweep.json", json.dumps({"config": config_dict(cfg), "runs": records}, indent=1))
    subprocess.run([sys.executable, str(EXAMPLES / "summarize_results.py"), f"out={cfg.out}"], check=True)
    failed = [r for r in records if r["exit_code"] != 0]
    if failed:
        raise SystemExit(f"{len(failed)} of {len(records)} runs failed: {[r['log'] for r in failed]}")


if __name__ == "__main__":
    main(sys.argv[1:])
