"""The main job over tasks and seeds, then the summary table: the benchmark protocol in one command.

    python examples/paper/sweep.py out=outputs/pipeline                       # 4 MetaWorld tasks x 3 seeds, FM
    python examples/paper/sweep.py tasks=[shelf-place] seeds=[1,2] policy=dp jobs=1 threads=2
    python examples/paper/sweep.py launcher=ray ray_address=auto threads=2 out=/shared/pipeline   # on a Ray cluster

Every run is its own ``examples/train_dp3_wm.py`` process, so a run that crashes does not stop
the others, and a stopped sweep resumes where it was (finished stages are skipped). Runs go
seed-major (every task's seed 0 first) ``jobs`` at a time with ``threads`` threads each; on a
2-core CPU two one-thread runs side by side use the cores better than one two-thread run.
Each run's output goes to ``<out>/logs/``; exit codes and wall times to ``<out>/sweep.json``.

With ``launcher=ray`` every run is a Ray task of ``threads`` CPUs instead (``pip install
"torchrl_dalir[ray]"``): on the cluster that ``ray_address`` names (``auto``: the one ``ray start``
runs on this machine), or on a local Ray instance of ``jobs * threads`` CPUs. Every node must see
this checkout, its Python and ``out`` at the same paths (a shared filesystem); the summary is made
from ``out`` as with the local launcher.
"""

from __future__ import annotations

import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import check_choice, config_dict, parse_config
from torchrl_dalir.pipeline import PRESETS, PipelineConfig
from torchrl_dalir.pipeline.records import config_variant
from torchrl_dalir.utils import atomic_write, ray_runtime, run_logged

EXAMPLES = Path(__file__).resolve().parents[1]  # examples/: the main job; the summary is beside this script
LAUNCHERS = ("local", "ray")


@dataclass
class Config:
    tasks: list[str] = field(default_factory=lambda: ["disassemble", "shelf-place", "stick-pull", "pick-place-wall"])
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    policy: str = "fm"
    preset: str = "cpu"
    out: str = "outputs/pipeline"
    jobs: int = 2  # runs side by side (with launcher=ray and a cluster: as many as its CPUs allow)
    threads: int = 1  # torch threads per run
    overrides: list[str] = field(default_factory=list)  # passed to every run, e.g. [eval_episodes=100]
    launcher: str = "local"  # local (processes here) | ray (one Ray task per run)
    ray_address: str = ""  # with launcher=ray: the cluster to join; "" starts a local instance

    def __post_init__(self):
        check_choice("launcher", self.launcher, LAUNCHERS)


def run_arguments(cfg: Config, task: str, seed: int) -> list[str]:
    return [
        f"task={task}",
        f"seed={seed}",
        f"policy={cfg.policy}",
        f"preset={cfg.preset}",
        f"out={cfg.out}",
        *cfg.overrides,
    ]


def run_one(cfg: Config, task: str, seed: int) -> dict:
    name = f"{task}_{cfg.policy}_seed{seed}"
    log = Path(cfg.out) / "logs" / f"{name}.log"
    code, seconds = run_logged(
        [sys.executable, str(EXAMPLES / "train_dp3_wm.py"), *run_arguments(cfg, task, seed)], log, cfg.threads
    )
    print(
        f"[sweep] {name}: {'ok' if code == 0 else f'FAILED (exit {code}), see {log}'} in {seconds / 60:.1f} min",
        flush=True,
    )
    return {
        "task": task,
        "seed": seed,
        "policy": cfg.policy,
        "exit_code": code,
        "seconds": round(seconds, 1),
        "log": str(log),
    }


def launch(cfg: Config, runs: list[tuple[str, int]]) -> list[dict]:
    """Runs every ``(task, seed)`` with ``cfg.launcher``; their records come back in the order of ``runs``."""
    if cfg.launcher == "local":
        with ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
            return list(pool.map(lambda run: run_one(cfg, *run), runs))
    init_config = (
        {"address": cfg.ray_address}
        if cfg.ray_address
        else {"num_cpus": cfg.jobs * cfg.threads, "include_dashboard": False}
    )
    with ray_runtime("launcher=ray", init_config) as ray:
        remote = ray.remote(num_cpus=cfg.threads)(run_one)
        return ray.get([remote.remote(cfg, *run) for run in runs])


def main(argv: list[str]) -> None:
    cfg = parse_config(Config, argv)
    runs = [(task, seed) for seed in cfg.seeds for task in cfg.tasks]
    for run in runs:  # a bad task, policy, preset or override fails now, not an hour into the sweep
        parse_config(PipelineConfig, run_arguments(cfg, *run), PRESETS)
    records = launch(cfg, runs)
    atomic_write(Path(cfg.out) / "sweep.json", json.dumps({"config": config_dict(cfg), "runs": records}, indent=1))
    variant = config_variant(
        parse_config(PipelineConfig, run_arguments(cfg, *runs[0]), PRESETS)
    )  # the summary's tables are of the runs' variant
    summarize = Path(__file__).resolve().parent / "summarize_results.py"
    subprocess.run([sys.executable, str(summarize), f"out={cfg.out}", f"variant={variant}"], check=True)
    failed = [r for r in records if r["exit_code"] != 0]
    if failed:
        raise SystemExit(f"{len(failed)} of {len(records)} runs failed: {[r['log'] for r in failed]}")


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
