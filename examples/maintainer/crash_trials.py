"""Kill -9 trials of the main job: a run killed at any point and resumed must give the same results.

    python examples/maintainer/crash_trials.py preset=smoke out=outputs/crash_trials \\
          # reach: a kill in each of the 7 stages
    python examples/maintainer/crash_trials.py preset=smoke seed=1 trials=2 reuse_reference=true \\
          # 14 more kills, same reference
    python examples/maintainer/crash_trials.py trials=7 job=[preset=cpu]  # the cpu preset, one kill per run: hours

Runs ``examples/train_dp3_wm.py`` once uninterrupted (``<out>/reference``), then ``trials`` times
(``<out>/trial_<i>``): each trial's run is killed with SIGKILL (its whole process group, collector
workers included) at a random moment inside a stage, started again and killed inside a later stage,
``kills`` times in all (the moment is drawn from the reference's time in that stage, counted from the
line with which the stage before it ended), then run to completion. Every artifact is then compared with the
reference's, exactly: datasets column by column, every checkpoint entry (policy, the world model's
stage checkpoints and final weights, the calibration stored in it), the calibration and evaluation
JSON and the results table. Wall times (``seconds``) and the run's own folder are not compared.

``max_steps`` shortens the task's episodes for these runs (most of a smoke run is simulation);
every stage still runs as in the main job. Writes ``<out>/crash_trials.json`` (per trial: the
stage killed, when, identical or not, the artifacts that differ and how) after every trial, and
prints a table.
"""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchrl_dalir.checkpoints import safe_torch_load
from torchrl_dalir.config import check_at_least, config_dict, parse_config
from torchrl_dalir.data import TrajectoryDataset
from torchrl_dalir.utils import atomic_write

JOB = Path(__file__).resolve().parents[1] / "train_dp3_wm.py"  # examples/train_dp3_wm.py
# the main job's line when a stage has run to its end (with its seconds), or was found done before
STAGE_LINE = re.compile(r"^\[(\w+)\] (?:(\d+) s -> |done before: )", re.MULTILINE)
IGNORED = {"seconds"}  # wall times: the only entries that may differ between identical runs


@dataclass
class Config:
    """Args:
    out: the runs (``reference``, ``trial_<i>``) and ``crash_trials.json``.
    task: the main job's task.
    max_steps: the episodes' step limit in these runs (0: the task's own).
    trials: killed-and-resumed runs.
    kills: kills per trial, in successive stages (7: one in every stage of a run with exploration data); trial
        ``i`` is first killed in the reference's stage ``i * kills`` (cycling through the stages).
    seed: draws each kill's moment, a fraction in ``within`` of the reference's time in the stage.
    job: further arguments of the main job (its preset and settings).
    timeout: seconds one run may take before the trials give up.
    reuse_reference: keep the uninterrupted run of an earlier call with the same settings (more trials, another
        ``seed``); only for an unchanged library.
    """

    out: str = "outputs/crash_trials"
    preset: str = "cpu"
    task: str = "reach"
    max_steps: int = 0
    trials: int = 7
    kills: int = 1
    seed: int = 0
    within: tuple[float, float] = (0.1, 0.9)
    job: list[str] = field(default_factory=lambda: ["preset=cpu"])
    timeout: float = 4 * 3600
    reuse_reference: bool = False

    def __post_init__(self):
        check_at_least("trials", self.trials, 1)
        check_at_least("kills", self.kills, 1)
        check_at_least("max_steps", self.max_steps, 0)
        if not 0 <= self.within[0] <= self.within[1] <= 1:
            raise ValueError(f"within must be two fractions 0 <= a <= b <= 1, got {self.within}")


QUIET = ["collection.progress=false", "policy_training.progress=false", "world_model.progress=false"]
PRESETS = {
    "cpu": {},
    # every stage, exploration data included, on reach with 80-step episodes (the expert succeeds in 40-60 steps)
    "smoke": {
        "max_steps": 80,
        "trials": 1,
        "kills": 7,
        "job": [
            "preset=smoke",
            "exploration_rollouts=1",
            "eval_methods=[base,dalir]",
            *QUIET,
        ],
    },
}


def job_command(cfg: Config, run_dir: Path) -> list[str]:
    """The main job for one run: through :func:`run_job` (``--job``) when the step limit is shortened."""
    args = [f"task={cfg.task}", *cfg.job, f"out={run_dir}"]
    if cfg.max_steps == 0:
        return [sys.executable, "-u", str(JOB), *args]
    return [sys.executable, "-u", __file__, "--job", cfg.task, str(cfg.max_steps), *args]


def run_job(task: str, max_steps: int, args: list[str]) -> None:
    """The main job with ``task``'s episodes cut to ``max_steps`` (in this process: smoke collections and
    evaluations step their envs here)."""
    import dataclasses
    import runpy

    from torchrl_dalir.envs import tasks

    tasks.TASKS[task] = dataclasses.replace(tasks.get_task(task), max_steps=max_steps)
    sys.argv = [str(JOB), *args]
    runpy.run_path(str(JOB), run_name="__main__")


def stage_lines(log: Path) -> list[tuple[str, str]]:
    """The stages that the run logging to ``log`` has passed (run to their end, or found done before), in order,
    each with the seconds it logged (``""`` for one done before)."""
    return STAGE_LINE.findall(log.read_text()) if log.exists() else []


def run(
    cfg: Config, run_dir: Path, log_name: str, kill: tuple[str | None, float] | None = None, times: dict | None = None
) -> dict:
    """Runs the main job into ``run_dir`` (output to ``<run_dir>/<log_name>``). With ``kill=(after, delay)``, kills
    its process group with SIGKILL ``delay`` seconds after stage ``after`` logged its end (or that it was done
    before; ``None``: after the start). ``times`` collects when each stage logged its end (seconds from the
    start). Returns the exit code, the seconds taken and, for a kill, the stages passed before it."""
    log = run_dir / log_name
    run_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    kill_at = start + kill[1] if kill is not None and kill[0] is None else None
    with log.open("w") as stream:  # its own process group, so that a kill reaches its collector workers
        process = subprocess.Popen(job_command(cfg, run_dir), stdout=stream, stderr=subprocess.STDOUT, process_group=0)
    try:
        seen = 0
        while process.poll() is None or seen < len(stage_lines(log)):
            now = time.perf_counter()
            if now - start > cfg.timeout:
                raise TimeoutError(f"{run_dir}: a run took over {cfg.timeout} s; see {log}")
            passed = stage_lines(log)
            for name, _ in passed[seen:]:
                if times is not None:
                    times[name] = round(now - start, 1)
                if kill is not None and kill_at is None and name == kill[0]:
                    kill_at = now + kill[1]
            seen = len(passed)
            if kill_at is not None and now >= kill_at and process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
                _check_group_gone(process.pid)
                return {
                    "exit_code": process.returncode,
                    "seconds": round(now - start, 1),
                    "passed": [n for n, _ in stage_lines(log)],
                }
            time.sleep(0.2)
    finally:
        if process.poll() is None:  # an error or a stop of this script: leave no job behind
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    return {"exit_code": process.returncode, "seconds": round(time.perf_counter() - start, 1)}


def _check_group_gone(pgid: int) -> None:
    """Waits until no process of the killed group is left (a worker that outlived the kill is an error)."""
    for _ in range(50):
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    raise RuntimeError(f"processes of the killed group {pgid} are still running")


# -- comparing two runs --------------------------------------------------------------------------------
def artifacts(root: Path) -> dict[str, Path]:
    """The artifacts of a run that results depend on, by path relative to ``root``: datasets (directories
    with a ``meta.json`` and ``rows``), checkpoints (``*.pt``), JSON and markdown results. Logs, files set
    aside by ``redo`` and temporary files are left out."""
    found = {}
    for path in sorted(root.rglob("*")):
        relative = path.relative_to(root)
        if any(part == "logs" or part.startswith(".") or ".replaced-" in part for part in relative.parts):
            continue
        if any(
            (parent / "rows").is_dir() and (parent / "meta.json").exists()
            for parent in path.parents
            if root in parent.parents
        ):
            continue  # inside a dataset: the dataset is compared as a whole
        if path.is_dir() and (path / "meta.json").exists() and (path / "rows").is_dir():
            found[str(relative)] = path
        elif path.is_file() and path.suffix in (".pt", ".json", ".md") and path.parent != root:
            found[str(relative)] = path
    return found


def differences(a, b, where: str = "") -> list[str]:
    """Where two loaded artifacts differ (exactly: tensors bit for bit), as readable entries."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{where}/{k}: only in {'reference' if k in a else 'trial'}" for k in sorted(set(a) ^ set(b), key=str)]
        for key in sorted(set(a) & set(b), key=str):
            if key not in IGNORED:
                out += differences(a[key], b[key], f"{where}/{key}")
        return out
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{where}[{i}]")]
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        if a.shape != b.shape or a.dtype != b.dtype:
            return [f"{where}: {tuple(a.shape)} {a.dtype} vs {tuple(b.shape)} {b.dtype}"]
        unequal = a != b if not a.is_floating_point() else ~((a == b) | (a.isnan() & b.isnan()))
        if unequal.any():
            rows = int(unequal.reshape(len(a), -1).any(-1).sum()) if a.dim() else 1
            return [f"{where}: {rows} of {len(a) if a.dim() else 1} rows differ"]
        return []
    return [] if type(a) is type(b) and a == b else [f"{where}: {a!r:.80} vs {b!r:.80}"]


def load_artifact(path: Path, root: Path):
    """An artifact as comparable values; strings naming the run's own folder are made folder-free."""
    if path.is_dir():
        dataset = TrajectoryDataset.load(path)
        meta = json.loads((path / "meta.json").read_text())
        content = {"rows": dict(dataset.rows.items(include_nested=True, leaves_only=True)), "meta": meta}
    elif path.suffix == ".pt":
        content = safe_torch_load(path)
    elif path.suffix == ".json":
        content = json.loads(path.read_text())
    else:
        content = path.read_text()
    return _without_root(content, str(root))


def _without_root(value, root: str):
    if isinstance(value, str):
        return value.replace(root, "<out>")
    if isinstance(value, dict):
        return {_without_root(k, root): _without_root(v, root) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_without_root(v, root) for v in value)
    return value


def compare_runs(reference: Path, trial: Path) -> dict[str, list[str]]:
    """Per artifact that is not the same in both runs (or missing from one), how it differs."""
    ours, theirs = artifacts(reference), artifacts(trial)
    differing = {
        name: ["missing from the trial" if name in ours else "not in the reference"]
        for name in sorted(set(ours) ^ set(theirs))
    }
    for name in sorted(set(ours) & set(theirs)):
        found = differences(load_artifact(ours[name], reference), load_artifact(theirs[name], trial))
        if found:
            differing[name] = found[:20]
    return differing


# -- the trials --------------------------------------------------------------------------------------
def reference_run(cfg: Config, reference_dir: Path) -> dict:
    """The uninterrupted run (reused with ``reuse_reference`` if it finished before) and each stage's span
    ``(start, end)`` in it, in seconds from its start (the start: its end less the seconds it logged)."""
    record = reference_dir / "stages.json"
    if cfg.reuse_reference and record.exists():
        return json.loads(record.read_text())
    shutil.rmtree(reference_dir, ignore_errors=True)
    ends: dict[str, float] = {}
    result = run(cfg, reference_dir, "job.log", times=ends)
    if result["exit_code"] != 0:
        raise SystemExit(f"the uninterrupted run failed (exit {result['exit_code']}); see {reference_dir / 'job.log'}")
    logged = dict(stage_lines(reference_dir / "job.log"))
    reference = {
        **result,
        "stages": {name: (round(max(end - int(logged[name]), 0.0), 1), end) for name, end in ends.items()},
    }
    atomic_write(record, json.dumps(reference, indent=1))
    return reference


def trial(cfg: Config, trial_dir: Path, index: int, spans: dict, rng: random.Random) -> dict:
    """One trial: the job killed in ``cfg.kills`` successive stages (from stage ``index * kills``, cycling), each
    time at a random moment of the stage, then resumed to completion and compared with the reference."""
    stages = list(spans)
    shutil.rmtree(trial_dir, ignore_errors=True)
    kills = []
    for k in sorted({(index * cfg.kills + j) % len(stages) for j in range(cfg.kills)}):
        fraction = rng.uniform(*cfg.within)
        previous_end = spans[stages[k - 1]][1] if k else 0.0
        delay = spans[stages[k]][0] - previous_end + fraction * (spans[stages[k]][1] - spans[stages[k]][0])
        killed = run(cfg, trial_dir, f"killed_{len(kills)}.log", kill=(stages[k - 1] if k else None, delay))
        passed = killed.get("passed", stages)
        kills.append(
            {
                "planned_stage": stages[k],
                "killed_in_stage": next((s for s in stages if s not in passed), None) if "passed" in killed else None,
                "fraction": round(fraction, 3),
                "killed_after_seconds": killed["seconds"],
            }
        )
    resumed = run(cfg, trial_dir, "resumed.log")
    if resumed["exit_code"] != 0:
        differing = {"resumed run": [f"exit {resumed['exit_code']}, see {trial_dir / 'resumed.log'}"]}
    else:
        differing = compare_runs(trial_dir.parent / "reference", trial_dir)
    return {
        "trial": index,
        "kills": kills,
        "resumed_seconds": resumed["seconds"],
        "identical": not differing,
        "differing": differing,
    }


def main(argv: list[str]) -> None:
    if argv[:1] == ["--job"]:
        return run_job(argv[1], int(argv[2]), argv[3:])
    cfg = parse_config(Config, argv, PRESETS)
    signal.signal(
        signal.SIGTERM, lambda *_: sys.exit(143)
    )  # a stopped script kills its running job too (run's finally)
    out = Path(cfg.out).resolve()
    rng = random.Random(cfg.seed)
    started = time.perf_counter()
    reference = reference_run(cfg, out / "reference")
    spans = reference["stages"]
    print(f"[crash_trials] reference: {reference['seconds']:.0f} s; stage spans (s) {spans}", flush=True)
    report = {"config": config_dict(cfg), "reference": reference, "trials": []}
    for i in range(cfg.trials):
        record = trial(cfg, out / f"trial_{i}", i, spans, rng)
        report["trials"].append(record)
        report["wall_seconds"] = round(time.perf_counter() - started, 1)
        atomic_write(out / "crash_trials.json", json.dumps(report, indent=1))
        stages = ", ".join(f"{k['killed_in_stage']} after {k['killed_after_seconds']:.0f} s" for k in record["kills"])
        verdict = "identical" if record["identical"] else "DIFFERENT: " + ", ".join(record["differing"])
        print(f"[crash_trials] trial {i}: killed in {stages} -> {verdict}", flush=True)

    print(
        "\n| trial | kill | stage killed | after (s) | identical | differing artifacts |"
        "\n| --- | --- | --- | --- | --- | --- |"
    )
    for r in report["trials"]:
        for j, k in enumerate(r["kills"]):
            verdict = (
                ("yes" if r["identical"] else "no", ", ".join(r["differing"]) or "-")
                if j == len(r["kills"]) - 1
                else ("", "")
            )
            print(
                f"| {r['trial']} | {j} | {k['killed_in_stage']} | {k['killed_after_seconds']:.0f} "
                f"| {verdict[0]} | {verdict[1]} |"
            )
    kills = [k for r in report["trials"] for k in r["kills"]]
    print(
        f"\n{sum(r['identical'] for r in report['trials'])} of {cfg.trials} trials identical "
        f"after {len(kills)} kills in stages "
        f"{sorted({k['killed_in_stage'] for k in kills if k['killed_in_stage']})}; "
        f"{report['wall_seconds'] / 60:.1f} min; "
        f"report: {out / 'crash_trials.json'}"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
