"""Paper Table 3: (a) what supervises the scorer, (b) how much mixed data the world model needs.

    python examples/paper/table3_diagnostics.py part=a out=outputs/pipeline  # Pen and disassemble, seed 0
    python examples/paper/table3_diagnostics.py part=b out=outputs/pipeline mixed_sizes=[100,200,0]
    python examples/paper/table3_diagnostics.py part=a tasks=[disassemble] seeds=[0,1] \\
        overrides=[world_model.encoder=finetune]

Each (task, seed) needs the main job's run (``examples/train_dp3_wm.py``, run here first if it is
missing; finished stages are skipped), which gives the base policy and DALI-R with the scorer of
sparse terminal labels. Each variant is that run with one world-model setting changed (its own
world model; the policy and data are shared), evaluated on the same test episodes with the
paper's arg-max (no calibration: the table compares supervision and data, not selection rules):

- (a) ``dense_reward``: the scorer learns the simulator's dense reward-to-go (an oracle the
  method does not need); rows: no scorer (the base policy), sparse terminal labels, dense reward.
- (b) ``mixed<N>``: the world model and scorer learn from ``N`` of the training trajectories
  (a nested random subset; the held-out trajectories stay the same, so the held-out latent MSE
  is comparable); ``0`` is all of them (the main job's own world model).

Runs go ``jobs`` at a time, each its own process (logs under ``<out>/logs/``). Writes
``<table_out>/table3<part>.md``, ``.json`` (per-seed numbers and every run's command) and ``.png``.
"""

from __future__ import annotations

import json
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from statistics import mean

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import check_choice, config_dict, parse_config
from torchrl_dalir.evaluation.compare import ARGMAX, BASE
from torchrl_dalir.evaluation.plots import plot_data_scale, plot_success_by_task
from torchrl_dalir.pipeline import PRESETS, PipelineConfig
from torchrl_dalir.utils import atomic_write, run_logged

EXAMPLES = Path(__file__).resolve().parents[1]  # examples/, where the main job is
PARTS = {"a": "scorer supervision", "b": "mixed-data scale"}
VARIANT_RUN = ["calibration_episodes=0", "eval_methods=[argmax]"]  # a variant's evaluation: the paper's arg-max alone


@dataclass
class Config:
    part: str = "a"  # a (scorer supervision) | b (mixed-data scale)
    tasks: list[str] = field(default_factory=list)  # empty: the paper's (a: pen and disassemble; b: disassemble)
    seeds: list[int] = field(default_factory=lambda: [0])
    mixed_sizes: list[int] = field(
        default_factory=lambda: [100, 200, 0]
    )  # (b) training trajectories per world model; 0: all
    policy: str = "fm"
    preset: str = "cpu"
    out: str = "outputs/pipeline"  # the main job's output folder, shared by every run
    overrides: list[str] = field(default_factory=list)  # passed to every run, e.g. [world_model.encoder=finetune]
    jobs: int = 2  # runs side by side
    threads: int = 1  # torch threads per run
    table_out: str = "outputs/table3"

    def __post_init__(self):
        check_choice("part", self.part, PARTS)
        self.tasks = self.tasks or (["pen", "disassemble"] if self.part == "a" else ["disassemble"])
        if self.part == "b" and (not self.mixed_sizes or min(self.mixed_sizes) < 0):
            raise ValueError(f"mixed_sizes must be non-negative trajectory counts (0: all), got {self.mixed_sizes}")


def variants(cfg: Config) -> dict[str, list[str]]:
    """The main-job settings of each variant's world model; ``""`` is the main job itself, always
    run (first): the variants reuse its policy and data."""
    if cfg.part == "a":
        return {"": [], "dense_reward": ["world_model.scorer_target=dense_reward"]}
    return {"": [], **{f"mixed{n}": [f"world_model.mixed_trajectories={n}"] for n in cfg.mixed_sizes if n}}


def run_arguments(cfg: Config, task: str, seed: int, variant: str) -> list[str]:
    own = variants(cfg)[variant]
    return [
        f"task={task}",
        f"seed={seed}",
        f"policy={cfg.policy}",
        f"preset={cfg.preset}",
        f"out={cfg.out}",
        *cfg.overrides,
        *own,
        *(VARIANT_RUN if variant else []),
    ]


def run(cfg: Config, task: str, seed: int, variant: str) -> dict:
    """One main-job process (its finished stages are skipped); its results and world-model metrics."""
    arguments = run_arguments(cfg, task, seed, variant)
    pipeline = parse_config(PipelineConfig, arguments, PRESETS)
    log = Path(cfg.out) / "logs" / f"table3_{task}_{pipeline.run_name()}.log"
    code, seconds = run_logged([sys.executable, str(EXAMPLES / "train_dp3_wm.py"), *arguments], log, cfg.threads)
    print(
        f"[table3] {task} {pipeline.run_name()}: "
        f"{'ok' if code == 0 else f'FAILED (exit {code}), see {log}'} in {seconds / 60:.1f} min",
        flush=True,
    )
    if code != 0:
        raise RuntimeError(f"the run {arguments} failed: see {log}")
    results = json.loads((pipeline.results_dir() / "results.json").read_text())
    return {
        "task": task,
        "seed": seed,
        "variant": variant,
        "command": ["python examples/train_dp3_wm.py", *arguments],
        "success": {name: r["success_rate"] for name, r in results["success"].items()},
        "episodes": results["success"][ARGMAX]["episodes"],
        "metrics": results["world_model_metrics"],
    }


def table_a(runs: list[dict], tasks: list[str]) -> list[dict]:
    """Per task the per-seed success of the base policy and of DALI-R with each scorer's supervision."""

    def rates(task, variant, method):
        return [r["success"][method] for r in runs if r["task"] == task and r["variant"] == variant]

    return [
        {
            "task": t,
            "base": rates(t, "", BASE),
            "sparse": rates(t, "", ARGMAX),
            "dense": rates(t, "dense_reward", ARGMAX),
        }
        for t in tasks
    ]


def table_b(runs: list[dict], cfg: Config) -> list[dict]:
    """Per task and data size: held-out latent MSE (and the "no change" predictor's) and DALI-R's
    success, per seed, beside the base policy's (the same policy for every size)."""
    rows = []
    for task in cfg.tasks:
        base = [r["success"][BASE] for r in runs if r["task"] == task and r["variant"] == "" and BASE in r["success"]]
        for n in cfg.mixed_sizes:
            chosen = [r for r in runs if r["task"] == task and r["variant"] == (f"mixed{n}" if n else "")]
            rows.append(
                {
                    "task": task,
                    "mixed_trajectories": n or "all",
                    "wm_mse": [r["metrics"]["wm_mse"] for r in chosen],
                    "no_change_mse": [r["metrics"]["no_change_mse"] for r in chosen],
                    "base": base,
                    "success": [r["success"][ARGMAX] for r in chosen],
                }
            )
    return rows


def markdown(cfg: Config, table: list[dict], episodes: int) -> str:
    footer = (
        f"\n\nMean over seeds {cfg.seeds}, {episodes} test episodes per seed; DALI-R selects by the paper's arg-max.\n"
    )
    if cfg.part == "a":
        labels = {
            "base": "no scorer (base policy)",
            "sparse": "sparse terminal labels",
            "dense": "dense simulator reward (oracle)",
        }
        lines = [
            "| supervision | " + " | ".join(row["task"] for row in table) + " | avg. |",
            "| --- |" + " --- |" * (len(table) + 1),
        ]
        for key, label in labels.items():
            cells = [100 * mean(row[key]) for row in table]
            lines.append(f"| {label} | " + " | ".join(f"{c:.1f}" for c in cells) + f" | {mean(cells):.1f} |")
        return "\n".join(lines) + footer
    lines = [
        "| task | mixed trajectories | held-out latent MSE | no-change MSE | base policy (%) | DALI-R (%) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in table:
        base = (
            f"{100 * mean(row['base']):.1f}" if row["base"] else "-"
        )  # (a main run evaluated without the base policy)
        lines.append(
            f"| {row['task']} | {row['mixed_trajectories']} | {mean(row['wm_mse']):.5f} "
            f"| {mean(row['no_change_mse']):.5f} | "
            f"{base} | {100 * mean(row['success']):.1f} |"
        )
    return "\n".join(lines) + footer


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    jobs = [(task, seed, variant) for seed in cfg.seeds for task in cfg.tasks for variant in variants(cfg)]
    for job in jobs:  # a bad task or override fails now, not an hour in
        parse_config(PipelineConfig, run_arguments(cfg, *job), PRESETS)
    main_runs = [job for job in jobs if not job[2]]
    with ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
        runs = list(pool.map(lambda job: run(cfg, *job), main_runs))
        runs += list(pool.map(lambda job: run(cfg, *job), [job for job in jobs if job[2]]))
    table = table_a(runs, cfg.tasks) if cfg.part == "a" else table_b(runs, cfg)
    text = markdown(cfg, table, runs[0]["episodes"])
    print(text)
    out = Path(cfg.table_out)
    name = f"table3{cfg.part}"
    atomic_write(out / f"{name}.md", text)
    atomic_write(
        out / f"{name}.json",
        json.dumps({"config": config_dict(cfg), "part": PARTS[cfg.part], "table": table, "runs": runs}, indent=1),
    )
    if cfg.part == "a":
        plot_success_by_task(
            table,
            out / f"{name}.png",
            title="Scorer supervision",
            methods=(("base", "no scorer"), ("sparse", "sparse labels"), ("dense", "dense reward (oracle)")),
        )
    else:
        plot_data_scale(table, out / f"{name}.png")


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
