"""The main job's stages in order: demos -> base policy -> mixed data -> (exploration data) ->
(branched outcomes) -> world model -> calibration -> evaluation, one task and seed.

Every stage writes an artifact under ``cfg.out`` and is skipped once that artifact is complete (a
dataset marked complete in its ``meta.json``, a training at its last step); an interrupted stage
resumes. ``redo=[world_model]`` runs that stage and the later ones again from scratch, keeping
the previous runs aside. Each finished stage adds a line to ``<out>/stages/<task>/<run name>.jsonl``
(the wall time of the attempt that finished it, the job's peak memory), which the run's record
keeps. ``examples/train_dp3_wm.py`` is this function behind a command line.
"""

from __future__ import annotations

import json
import sys
import time
from functools import partial
from pathlib import Path

from torchrl_dalir.branching.outcomes import collect_branched
from torchrl_dalir.checkpoints import (
    load_policy,
    load_world_model,
    safe_torch_load,
    save_chunk_critic,
    store_selection,
    training_finished,
)
from torchrl_dalir.config import config_dict
from torchrl_dalir.data import Source, collect
from torchrl_dalir.data.storage import is_complete
from torchrl_dalir.evaluation.calibration import GRIDS, calibrate, calibrate_on_failures
from torchrl_dalir.evaluation.compare import BASE, DALIR, p_better, paired_sign_test
from torchrl_dalir.pipeline.config import BRANCHED_SEED_BASE, STAGES, PipelineConfig
from torchrl_dalir.pipeline.report import evaluate_and_report
from torchrl_dalir.reranking.selection import SelectionConfig
from torchrl_dalir.training import train_policy, train_world_model
from torchrl_dalir.training.logging import log_results
from torchrl_dalir.training.policy import exploration_actor, policy_actor
from torchrl_dalir.training.ranking import RankingTrainingConfig, fit_critic
from torchrl_dalir.utils import atomic_write


def stage(name: str, cfg: PipelineConfig, artifact: Path, run, finished=Path.exists) -> None:
    """Runs ``run`` unless ``finished(artifact)`` (a stage that ran to its end; an interrupted one runs again and
    resumes). A stage in ``cfg.redo`` starts from scratch: its directory (the artifact's parent) is first moved
    aside to ``<dir>.replaced-<time>``. Stages after ``cfg.until`` are not run."""
    if STAGES.index(name) > STAGES.index(cfg.until):
        return
    if name in cfg.redo and artifact.parent.exists():
        aside = artifact.parent.with_name(f"{artifact.parent.name}.replaced-{time.strftime('%Y%m%d-%H%M%S')}")
        artifact.parent.rename(aside)
        print(f"[{name}] redo: the previous run is kept in {aside}")
    elif finished(artifact):
        print(f"[{name}] done before: {artifact}")
        return
    start = time.perf_counter()
    run()
    seconds, memory = time.perf_counter() - start, peak_memory()
    print(f"[{name}] {seconds:.0f} s -> {artifact} ({describe_memory(memory)})", flush=True)
    log_stage(cfg, name, seconds, memory)


def log_stage(cfg: PipelineConfig, name: str, seconds: float, memory: tuple[float, float] | None) -> None:
    """Appends the finished stage's wall time (of the attempt that finished it: an interrupted attempt
    logs nothing) and the job's peak memory so far to ``<out>/stages/<task>/<run name>.jsonl``, a
    file per run so that jobs sharing ``out`` never write to one file. A redone stage adds another
    line; the last one counts."""
    own, workers = (None, None) if memory is None else (round(m, 2) for m in memory)
    line = {
        "run": f"{cfg.task}/{cfg.run_name()}",
        "stage": name,
        "seconds": round(seconds, 1),
        "peak_memory_gib": own,
        "workers_peak_memory_gib": workers,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    path = cfg.stage_log_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+b") as log:  # (appends go to the end whatever the position read)
        cut = False
        if log.seek(0, 2) > 0:
            log.seek(-1, 2)
            cut = log.read(1) != b"\n"  # a line a crash cut short
        log.write((("\n" if cut else "") + json.dumps(line) + "\n").encode())


def peak_memory() -> tuple[float, float] | None:
    """The job's high-water marks of resident memory so far in GiB: this process and its largest
    finished child (collector workers); ``None`` where it cannot be read (not on POSIX)."""
    try:
        import resource
    except ImportError:
        return None
    unit = 2**30 if sys.platform == "darwin" else 2**20  # ru_maxrss is in bytes on macOS, KiB on Linux
    return tuple(resource.getrusage(who).ru_maxrss / unit for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))


def describe_memory(memory: tuple[float, float] | None) -> str:
    """Printed after each stage, so the stage that raised a high-water mark shows."""
    return "peak memory unknown" if memory is None else f"peak memory {memory[0]:.1f} GiB, workers {memory[1]:.1f} GiB"


def run_pipeline(cfg: PipelineConfig) -> Path:
    """Runs every stage of ``cfg`` up to ``cfg.until``, skipping finished ones; returns the
    results folder (``results.md``, ``results.json``, diagnostic plots)."""
    data = cfg.collection
    common = data.collection_kwargs()
    policy_path = cfg.policy_training.run_dir() / "checkpoint.pt"
    world_model_path = cfg.world_model.run_dir() / "world_model.pt"
    results = cfg.results_dir()

    # 1. Expert demos: successful expert trajectories only, the same for every training seed.
    # (a dataset is done once its meta.json marks it complete, not when its rows exist: the two are not written at once)
    stage(
        "demos",
        cfg,
        data.demos_dir() / "meta.json",
        lambda: collect(
            cfg.task,
            data.demos_dir(),
            [Source("expert", data.num_demos)],
            seed=cfg.demo_seed,
            successes_only=True,
            **common,
        ),
        finished=dataset_finished,
    )

    # 2. The base policy learns from the demos alone (the data asymmetry).
    # (an interrupted training leaves a checkpoint behind: the stage resumes it)
    stage(
        "policy",
        cfg,
        policy_path,
        lambda: train_policy(cfg.policy_training),
        finished=trained_as_asked("policy", cfg.policy_training.resolved(), training_finished),
    )

    # 3. Mixed-quality data: noisy experts and rollouts of the trained base policy, all labeled.
    base_rollouts = Source(
        "base_policy", cfg.base_policy_rollouts, policy=partial(policy_actor, str(policy_path)), expert=False, history=2
    )
    stage(
        "mixed",
        cfg,
        data.mixed_dir() / "meta.json",
        lambda: collect(
            cfg.task,
            data.mixed_dir(),
            [*data.mixed_sources(), base_rollouts],
            seed=2 * cfg.seed + 1,
            noise_correlation=data.noise_correlation,
            **common,
        ),
        finished=dataset_finished,
    )

    # 3b. Optional exploration data: the base policy acting on point-dropout views.
    if cfg.exploration_rollouts > 0:
        explore = Source(
            "exploration",
            cfg.exploration_rollouts,
            policy=partial(exploration_actor, str(policy_path), cfg.dropout, cfg.seed),
            expert=False,
            history=2,
        )
        stage(
            "exploration",
            cfg,
            data.task_dir() / cfg.exploration_name() / "meta.json",
            lambda: collect(
                cfg.task, data.task_dir() / cfg.exploration_name(), [explore], seed=2 * cfg.seed + 2, **common
            ),
            finished=dataset_finished,
        )

    # 3c. Optional branched outcomes: which of a decision's candidates, each run from the same state, succeeds.
    if cfg.branched_episodes > 0:
        stage(
            "branched",
            cfg,
            cfg.branched_dir() / "meta.json",
            lambda: branch_and_rank(cfg, policy_path),
            finished=partial(branched_finished, cfg),
        )

    # 4. Latent encoder, task-completion scorer and latent world model, the policy frozen.
    stage(
        "world_model",
        cfg,
        world_model_path,
        lambda: train_world_model(cfg.world_model),
        finished=trained_as_asked("world_model", cfg.world_model, Path.exists),
    )

    # 5. The selection rule's setting, chosen on validation episodes and stored in the world model.
    # (done only if the world model holds this calibration: a retrained world model is calibrated again)
    calibration = cfg.calibration_dir() / "calibration.json"
    stage(
        "calibration",
        cfg,
        calibration,
        lambda: calibrate_and_record(cfg, policy_path, world_model_path, calibration),
        finished=lambda path: (
            path.exists() and json.loads(path.read_text()) == load_world_model(world_model_path).calibration
        ),
    )

    # 6. Base policy, DALI-R (calibrated rule and the paper's arg-max) and the random-candidate
    #    control on the same test episodes.
    # (done only if DALI-R was evaluated with the rule that the world model now names)
    stage(
        "evaluation",
        cfg,
        results / "results.json",
        lambda: evaluate_and_log(cfg, policy_path, world_model_path),
        finished=lambda path: (
            path.exists() and evaluated_rule(path) in (None, load_world_model(world_model_path).selection.name)
        ),
    )
    if cfg.until == STAGES[-1]:
        print((results / "results.md").read_text())
    return results


# Settings that say where a training writes, on what device, or how it reports; not what it learns.
NOT_LEARNED = frozenset(
    {
        "out",
        "data",
        "device",
        "precision",
        "checkpoint_every",
        "log_every",
        "wandb",
        "progress",
        "preset",
        "policy_checkpoint",
    }
)


def trained_as_asked(name: str, config, done) -> callable:
    """The ``finished`` test of training stage ``name``: ``done(checkpoint)``, once the checkpoint
    was trained with ``config``'s settings. A checkpoint trained with other settings (a folder of
    an earlier preset, say: its name does not hold every setting) is refused, naming them, instead
    of being used or resumed as if it were this job's."""
    asked = json.loads(json.dumps(config_dict(config)))

    def finished(path: Path) -> bool:
        if not path.exists():
            return False
        stored = json.loads(json.dumps(safe_torch_load(path, f"{name} checkpoint").get("config") or {}))
        differ = sorted(key for key in (asked.keys() & stored.keys()) - NOT_LEARNED if stored[key] != asked[key])
        if differ:
            settings = ", ".join(f"{key}={stored[key]!r} (this job: {asked[key]!r})" for key in differ)
            raise ValueError(
                f"{path} was trained with {settings}: pass redo=[{name}] to train it again with this job's "
                "settings (the previous run is kept aside), or choose another out="
            )
        return done(path)

    return finished


def branch_and_rank(cfg: PipelineConfig, policy_path: Path) -> None:
    """The branched stage: collects (or resumes) the branched outcomes, then, with two episodes or more, fits a
    chunk critic on them (:func:`~torchrl_dalir.training.ranking.fit_critic`: the loss with the higher out-of-fold
    within-decision AUC, trained on every decision) and writes its metrics (``ranking.json``) and the critic
    (``critic.pt``: ``calibration_grid=critic``, or ``RerankingActor(policy, critic=load_chunk_critic(path))``)."""
    policy = load_policy(policy_path, cfg.device)
    reranking = cfg.reranking().updated(num_candidates=cfg.branched_candidates)
    seed = BRANCHED_SEED_BASE + 1000 * cfg.seed
    outcomes = collect_branched(
        policy,
        cfg.branched_dir(),
        reranking,
        episodes=cfg.branched_episodes,
        stride=cfg.branched_stride,
        decisions=cfg.branched_decisions,
        seed=seed,
        progress=cfg.collection.progress,
        device=cfg.device,
    )
    if cfg.branched_episodes >= 2:
        critic, metrics = fit_critic(outcomes, policy, RankingTrainingConfig(seed=cfg.seed), device=cfg.device)
        atomic_write(cfg.branched_dir() / "ranking.json", json.dumps(metrics, indent=1))
        save_chunk_critic(cfg.branched_dir() / "critic.pt", critic, policy, metrics)  # last: it marks the stage done
        chosen = metrics["out_of_fold"][metrics["variant"]]
        print(
            f"[branched] {outcomes}: critic {metrics['variant']}, out-of-fold within-decision AUC "
            f"{chosen['auc']:.3f} on {chosen['split_decisions']} split decisions"
        )


def branched_finished(cfg: PipelineConfig, meta_path: Path) -> bool:
    """The outcomes are complete, of the job's plan (another plan runs the stage, which refuses the folder) and,
    if a critic is trained on them, it is written (a kill in between trains it again)."""
    if not meta_path.exists():
        return False
    meta = json.loads(meta_path.read_text())
    plan = (meta.get("num_candidates"), meta.get("episodes"), meta.get("stride"), meta.get("decisions", 0))
    wanted = (cfg.branched_candidates, cfg.branched_episodes, cfg.branched_stride, cfg.branched_decisions)
    if not meta.get("complete") or plan != wanted:
        return False
    return cfg.branched_episodes < 2 or (meta_path.parent / "critic.pt").exists()


def dataset_finished(meta_path: Path) -> bool:
    """Whether the dataset whose ``meta.json`` is ``meta_path`` is complete."""
    return is_complete(meta_path.parent)


def calibrate_and_record(cfg: PipelineConfig, policy_path: Path, world_model_path: Path, out: Path) -> None:
    """Chooses the selection rule's setting on validation episodes (``calibration_episodes=0``:
    the paper's arg-max) and stores it in the world model; the record also goes to ``out``."""
    if cfg.calibration_episodes > 0:
        common = dict(
            grid=GRIDS[cfg.calibration_grid],
            alpha=cfg.calibration_alpha,
            seed=cfg.calibration_seed,
            test_seed=cfg.eval_seed,
            device=cfg.device,
            reranking=cfg.reranking(),
            actor_seed=cfg.seed,
            critic=cfg.critic(),
        )
        if cfg.calibration_design == "failures":
            record = calibrate_on_failures(policy_path, world_model_path, failures=cfg.calibration_failures, **common)
        else:
            record = calibrate(
                policy_path,
                world_model_path,
                episodes=cfg.calibration_episodes,
                confirm_episodes=cfg.calibration_confirm_episodes,
                **common,
            )
        print(f"[calibration] chosen on {record['episodes']} validation episodes: {record['chosen']}", flush=True)
    else:
        record = {"chosen": SelectionConfig().name, "episodes": 0}
        store_selection(world_model_path, SelectionConfig(), record)
    atomic_write(out, json.dumps(record, indent=1))
    log_calibration(cfg, record)


def evaluated_rule(results_path: Path) -> str | None:
    """The selection rule with which a finished evaluation ran DALI-R (``None``: it did not)."""
    success = json.loads(results_path.read_text())["success"]
    return success[DALIR].get("selection", "argmax(state)") if DALIR in success else None  # earlier runs: the arg-max


def log_calibration(cfg: PipelineConfig, record: dict) -> None:
    """With ``cfg.wandb`` on, the calibration's results go to a wandb run ``<task>_<run name>_calibration``
    saved under the calibration folder: ``calibration/base_success_rate`` (the base policy on the
    validation episodes), per grid entry ``calibration/<entry>/success_rate`` (the ``failures``
    design: ``estimated_gain``) and ``calibration/<entry>/p_one_sided`` (the sign-test p-value
    against the base policy that ``calibration_alpha`` bounds), the confirmation's
    ``success_rate``, ``base_success_rate``, ``p_one_sided`` and ``confirmed`` (1 or 0), and
    ``calibration/chosen_is_base``; the chosen setting, the design, alpha and the episode count are
    the run's configuration. ``wandb=off``: nothing (``calibration.json`` holds it all)."""
    if cfg.wandb == "off":
        return

    def p_one_sided(vs_base: dict) -> float:
        return p_better(vs_base["base_only"], vs_base["dalir_only"])

    numbers = {"calibration/base_success_rate": record["base_success_rate"]} if "base_success_rate" in record else {}
    for entry in record.get("entries", []):
        for key in ("success_rate", "estimated_gain"):
            if key in entry:
                numbers[f"calibration/{entry['name']}/{key}"] = entry[key]
        if "vs_base" in entry:
            numbers[f"calibration/{entry['name']}/p_one_sided"] = p_one_sided(entry["vs_base"])
    confirmation = record.get("confirmation")
    if confirmation:
        for key in ("success_rate", "base_success_rate"):
            numbers[f"calibration/confirmation/{key}"] = confirmation[key]
        numbers["calibration/confirmation/p_one_sided"] = p_one_sided(confirmation["vs_base"])
        numbers["calibration/confirmation/confirmed"] = float(confirmation["confirmed"])
    numbers["calibration/chosen_is_base"] = float(record["chosen"] == GRIDS[cfg.calibration_grid][0].name)  # margin 1
    details = {
        "chosen": record["chosen"],
        "design": record.get("design", "fixed"),
        "alpha": record.get("alpha"),
        "episodes": record["episodes"],
        "grid": cfg.calibration_grid,
        "seed": record.get("seed"),
    }
    log_results(cfg.calibration_dir(), f"{cfg.task}_{cfg.run_name()}_calibration", cfg.wandb, numbers, details)


def evaluate_and_log(cfg: PipelineConfig, policy_path: Path, world_model_path: Path) -> None:
    """The evaluation stage: :func:`~torchrl_dalir.pipeline.report.evaluate_and_report`, then, with
    ``cfg.wandb`` on, its results to a wandb run ``<task>_<run name>_evaluation`` saved under the
    results folder: per method ``evaluation/<method>/success_rate`` on the test episodes and, for
    every method but the base policy, ``evaluation/<method>/p_two_sided`` (the paired sign test
    against the base policy, as in ``results.md``); the episode count, evaluation seed and DALI-R's
    selection rule are the run's configuration."""
    evaluate_and_report(cfg, policy_path, world_model_path)
    if cfg.wandb == "off":
        return
    success = json.loads((cfg.results_dir() / "results.json").read_text())["success"]
    base = [r["success"] for r in success[BASE]["records"]] if BASE in success else None
    numbers = {}
    for name, row in success.items():
        numbers[f"evaluation/{name}/success_rate"] = row["success_rate"]
        if base is not None and name != BASE:
            test = paired_sign_test(base, [r["success"] for r in row["records"]])
            numbers[f"evaluation/{name}/p_two_sided"] = test["p_value"]
    details = {
        "episodes": cfg.eval_episodes,
        "eval_seed": cfg.eval_seed,
        "selection": success.get(DALIR, {}).get("selection"),
    }
    log_results(cfg.results_dir(), f"{cfg.task}_{cfg.run_name()}_evaluation", cfg.wandb, numbers, details)
