"""Scorer-benchmark files for many runs: each run's five stages in one command, resumable.

    python examples/paper/scorer_benchmark_runs.py tasks=[stick-pull,disassemble] seeds=[0] policy=fm
    python examples/paper/scorer_benchmark_runs.py tasks=[pick-place-wall] policy=dp episodes=30 jobs=1

For every ``(task, seed)``, stage after stage, each its own process with ``threads`` torch threads (``jobs``
tasks side by side, each task's seeds in turn):

1. the base policy (``examples/train_dp3_wm.py ... until=policy``);
2. the first ``decisions`` decisions (default 1) of ``episodes`` data seeds branched, ``num_candidates``
   point-dropout candidates each (``branched_ranking.py``);
3. every decision's candidates continued under ``draws`` further noise draws, with the honest ceiling
   (``outcome_noise.py``: ``docs/results/honest_ceiling_<run>.json``);
4. the benchmark file ``benchmarks/scorer/<run>.pt``; 5. its distillation file ``benchmarks/scorer/distill/<run>.pt``;

and with ``evaluate=true`` the preregistered protocol on it (``docs/results/student_screen_prereg*.json``):

6. the ladder, ``docs/results/scorer_benchmark_<run>.json`` (``scorer_benchmark.py files=[...]``);
7. the validation screen, ``student_screen_<run>.json`` (``critic_screen.py student=... seed=1``);
8. only if the screen passed (:func:`~torchrl_dalir.evaluation.compare.screen_passed`), the test episodes,
   ``student_test_<run>.json`` (``seed=0 test=true``). Then ``python examples/paper/student_summary.py``.

A stage whose artifact is whole is skipped, so a stopped command resumes where it was (branching and the redraws resume
within their decisions, too). The files go to ``<results>/docs/results/`` and ``<results>/benchmarks/scorer/``
(default ``results=out``; ``results=.`` adds them to this checkout, where a run whose files are committed counts
as done, whatever policy ``out`` holds). Each run's output goes to ``<out>/logs/<run>.log``; exit codes and wall
times per stage to ``<out>/scorer_benchmark_runs.json``. Then ``python examples/paper/scorer_benchmark.py`` measures
the ladder on every file. About 70 min of one CPU thread per FM run of 100 episodes (the redraws are
two thirds of it).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.checkpoints.files import training_finished
from torchrl_dalir.config import check_at_least, check_choice, config_dict, parse_config
from torchrl_dalir.envs.tasks import TASKS
from torchrl_dalir.evaluation.compare import screen_passed
from torchrl_dalir.utils import atomic_write, run_logged

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "examples" / "paper"


@dataclass
class Config:
    tasks: list[str] = field(default_factory=lambda: ["stick-pull", "disassemble"])
    seeds: list[int] = field(default_factory=lambda: [0])
    policy: str = "fm"  # fm | dp
    episodes: int = 100  # branched episodes (data seeds 500000, ...)
    decisions: int = 1  # each episode's first decisions, branched and distilled (> 1: runs named <run>_d<decisions>)
    num_candidates: int = 8  # K (another K: runs named <run>_k<K>)
    draws: list[int] = field(default_factory=lambda: [1, 2, 3])  # further noise draws (M = 1 + len(draws))
    states: int = 1000  # distillation states (data seeds 600000, ...)
    out: str = "outputs/scorer_benchmark"  # policies, branched folders and logs
    results: str = ""  # where docs/results/ and benchmarks/scorer/ go ("": under out; "." adds them to this checkout)
    evaluate: bool = False  # then the ladder, the validation screen and, if it passed, the test episodes
    eval_episodes: int = 100  # the screen's and the test's episodes (evaluation seeds 1 and 0)
    jobs: int = 2
    threads: int = 1

    def __post_init__(self):
        check_choice("policy", self.policy, ("fm", "dp"))
        for name, minimum in (
            ("episodes", 1), ("decisions", 1), ("num_candidates", 2), ("states", 1), ("eval_episodes", 1), ("jobs", 1),
            ("threads", 1),
        ):  # fmt: skip
            check_at_least(name, getattr(self, name), minimum)
        for task in self.tasks:
            check_choice("task", task, tuple(TASKS))
        if not self.draws:
            raise ValueError(
                "draws= needs at least one further noise draw: the honest ceiling is cross-fitted over draws"
            )


def variant(cfg: Config) -> str:
    """What sets a run's decisions apart from the default's: ``_d<decisions>`` where later decisions are branched,
    ``_k<K>`` where the candidates are not the default's (``""`` for the first decision with 8 candidates)."""
    return (f"_d{cfg.decisions}" if cfg.decisions > 1 else "") + (
        f"_k{cfg.num_candidates}" if cfg.num_candidates != Config.num_candidates else ""
    )


def run_name(cfg: Config, task: str, seed: int) -> str:
    return f"{cfg.policy}_{task.replace('-', '_')}_s{seed}{variant(cfg)}"


def _branched_complete(folder: Path) -> bool:
    meta = folder / "meta.json"
    return meta.exists() and json.loads(meta.read_text()).get("complete", False)


def _screen_failed(screen: Path) -> str | bool:
    """``"screen failed"`` where the run's screen ran and failed the preregistered rule (its test is never run)."""
    if screen.exists() and not screen_passed(json.loads(screen.read_text())["paired"]):
        return "screen failed"
    return False


def stages(cfg: Config, task: str, seed: int) -> list[tuple[str, Callable[[], bool | str], list[str]]]:
    """The run's stages in order: ``(name, done, command)``. A stage is done when its artifact is whole: the
    policy's last training step, a complete branched collection, a file (each written atomically); the test
    also when the screen failed (``done`` then says why)."""
    out, run = Path(cfg.out), run_name(cfg, task, seed)
    results = Path(cfg.results or out)
    policy = out / "policies" / task / f"{cfg.policy}_seed{seed}" / "checkpoint.pt"
    branched_out = out / f"branched{variant(cfg)}"  # another K or decisions: another collection
    branched = branched_out / task / policy.parent.name / "dropout"
    redraws = results / "docs" / "results" / f"honest_ceiling_{run}.json"
    benchmark = results / "benchmarks" / "scorer" / f"{run}.pt"
    distillation = benchmark.parent / "distill" / f"{run}.pt"
    ladder, screen, test = (results / "docs" / "results" / f"{name}_{run}.json" for name in (
        "scorer_benchmark", "student_screen", "student_test"))  # fmt: skip
    python = [sys.executable]
    screening = [*python, str(PAPER / "critic_screen.py"), f"policy={policy}", f"student={benchmark}",
                 f"episodes={cfg.eval_episodes}", f"decisions={cfg.decisions}", "progress=false"]  # fmt: skip
    evaluation = [
        ("ladder", ladder.exists,
         [*python, str(PAPER / "scorer_benchmark.py"), f"files=[{benchmark}]", f"json={ladder}"]),
        ("screen", screen.exists, [*screening, "seed=1", f"out={out / 'student_screen'}", f"json={screen}"]),
        ("test", lambda: test.exists() or _screen_failed(screen),
         [*screening, "seed=0", "test=true", f"out={out / 'student_test'}", f"json={test}"]),
    ]  # fmt: skip
    return [
        (
            "policy",
            lambda: training_finished(policy),
            [*python, str(ROOT / "examples" / "train_dp3_wm.py"), f"task={task}", f"seed={seed}",
             f"policy={cfg.policy}", "until=policy", f"out={out}"],
        ),
        (
            "branching",
            lambda: _branched_complete(branched),
            [*python, str(PAPER / "branched_ranking.py"), f"policy={policy}", f"episodes={cfg.episodes}",
             "stride=1", f"decisions={cfg.decisions}", f"num_candidates={cfg.num_candidates}", "variants=[]",
             f"out={branched_out}"],
        ),
        (
            "redraws",
            redraws.exists,
            [*python, str(PAPER / "outcome_noise.py"), f"policy={policy}", f"branched={branched}",
             f"draws=[{','.join(map(str, cfg.draws))}]", "only_split=false", f"json={redraws}"],
        ),
        (
            "benchmark",
            benchmark.exists,
            [*python, str(PAPER / "scorer_benchmark.py"), f"build={benchmark}", f"policy={policy}",
             f"branched={branched}", f"redraws={redraws}"],
        ),
        (
            "distillation",
            distillation.exists,
            [*python, str(PAPER / "scorer_benchmark.py"), f"distill={distillation}", f"policy={policy}",
             f"states={cfg.states}", "seed=600000", f"num_candidates={cfg.num_candidates}",
             f"decisions={cfg.decisions}"],
        ),
    ] + (evaluation if cfg.evaluate else [])  # fmt: skip


def run_one(cfg: Config, task: str, seed: int) -> dict:
    """The run's stages that are not done yet, in order; stops at the first that fails."""
    run = run_name(cfg, task, seed)
    log = Path(cfg.out) / "logs" / f"{run}.log"
    record = {"run": run, "task": task, "seed": seed, "policy": cfg.policy, "log": str(log), "stages": {}}
    for name, done, command in stages(cfg, task, seed):
        if reason := done():
            record["stages"][name] = reason if isinstance(reason, str) else "done before"
            continue
        code, seconds = run_logged(command, log, cfg.threads)
        record["stages"][name] = {"exit_code": code, "seconds": round(seconds, 1)}
        print(f"[{run}] {name}: {'ok' if code == 0 else f'FAILED (exit {code}), see {log}'} in {seconds / 60:.1f} min")
        if code != 0 or not done():
            record["failed"] = name
            break
    return record


def main(argv: list[str]) -> list[dict]:
    cfg = parse_config(Config, argv)
    # one worker per task runs its seeds in turn: two runs of a task at once would collect into one demos folder
    with ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
        per_task = pool.map(lambda task: [run_one(cfg, task, seed) for seed in cfg.seeds], cfg.tasks)
        records = [record for records in per_task for record in records]
    summary = Path(cfg.out) / "scorer_benchmark_runs.json"
    atomic_write(summary, json.dumps({"config": config_dict(cfg), "runs": records}, indent=1))
    failed = [r for r in records if "failed" in r]
    if failed:
        raise SystemExit(f"{len(failed)} of {len(records)} runs failed: {[r['log'] for r in failed]}")
    return records


if __name__ == "__main__":
    main(sys.argv[1:])
