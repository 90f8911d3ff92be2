"""Collecting labeled trajectories with TorchRL collectors into an on-disk dataset.

A collection is a list of :class:`Source`\\ s (a policy, a drift-noise scale, a number of
trajectories). Each source is split into chunks; a chunk is collected by TorchRL collector workers
that each step one env and one copy of the policy (rendering and acting stay in the worker; this
process only gathers): a local ``MultiSyncCollector`` (``backend="local"``) or a ``RayCollector``
(``backend="ray"``, on the machines of a Ray cluster). A chunk is stored as soon as it is finished,
so an interrupted collection resumes at its first unfinished chunk.

Episode ``i`` of a chunk (its ``i``-th attempt) resets with seed ``chunk seed + i``, and its drift noise
and its policy's sampling restart from that seed at the reset: an episode depends on its seed only, never
on which worker ran it, on what that worker ran before, or on the process's random state. The chunk keeps
its attempts in seed order (with ``successes_only``, the successful ones), so its rows are the same
whatever the backend and the number of workers, interrupted or not. Worker ``w`` of ``W`` runs attempts
``w``, ``w + W``, ...; attempts run beyond the ones kept are dropped. Stored actions are the executed
ones, clipped to the env's action bounds.
"""

from __future__ import annotations

import sys
import time
import warnings
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import SerialEnv
from tqdm.auto import tqdm

from torchrl_dalir import keys
from torchrl_dalir.config import check_at_least, check_choice
from torchrl_dalir.data.labels import trajectory_rows
from torchrl_dalir.data.storage import DatasetMeta, DatasetWriter, TrajectoryDataset
from torchrl_dalir.envs import TaskSpec, action_bounds, get_task, make_env
from torchrl_dalir.experts import DriftNoise, make_expert
from torchrl_dalir.seeds import check_data_seed
from torchrl_dalir.utils import ray_runtime

SEEDS_PER_DATASET = 1_000_000  # chunk c of dataset seed s resets its episodes with s * 1e6 + c * 1e3 + attempt
SEEDS_PER_CHUNK = 1_000  # hence at most this many attempts per chunk
FRAMES_PER_WORKER = 64  # env steps per worker between two gathers
POLICY_SEED_OFFSET = 1 << 40  # an episode's policy samples from its seed + this: a stream apart from its drift noise's
BACKENDS = ("local", "ray")
RAY_ACTOR_RESOURCES = {"num_cpus": 1}  # a collector actor steps one env (no GPU, no memory reservation)


@dataclass
class Source:
    """Where trajectories come from.

    Args:
        name: a label stored with every trajectory (``"expert"``, ``"base_policy"``, ...).
        num_trajectories: how many trajectories to keep from this source.
        noise_scale: drift-noise scale added to the policy's actions (0 for none).
        policy: a picklable factory (a module-level function or a ``functools.partial``) that returns
            a TorchRL policy; each collector worker calls it once. ``None`` uses the task's expert.
            A policy with a ``reset(seed)`` method (the base policies and their actors) is seeded
            at every episode start from the episode's seed; any other one must not draw from torch's
            global generator.
        expert: whether the clean policy is the expert; its noise-free successes are tagged
            ``expert``, every other success ``imperfect_success``.
        history: the observation history the policy reads (2 for the base policies). The env
            then stacks observations (in a ``SerialEnv(1)``); only the newest frame is stored.

    Example:
        >>> Source("expert_noise_0.2", 200, noise_scale=0.2).describe()  # what the dataset's meta.json records
        {'name': 'expert_noise_0.2', 'num_trajectories': 200, 'noise_scale': 0.2, 'expert': True}
        >>> sources = [Source("expert", 200), Source("expert_noise_0.2", 200, noise_scale=0.2)]
        >>> mixed = collect("disassemble", "data/disassemble/mixed", sources, seed=1)  # doctest: +SKIP
    """

    name: str
    num_trajectories: int
    noise_scale: float = 0.0
    policy: Callable[[], Callable] | None = None
    expert: bool = True
    history: int = 1

    def describe(self) -> dict:
        return {
            "name": self.name,
            "num_trajectories": self.num_trajectories,
            "noise_scale": self.noise_scale,
            "expert": self.expert,
        }


def _worker_env(task: TaskSpec, first_seed: int, stride: int, num_points: int, history: int):
    """Worker ``w`` of ``stride``: its episodes reset with ``first_seed``, ``first_seed + stride``, ..."""
    make = partial(make_env, task, seed=first_seed, seed_stride=stride, num_points=num_points, history=history)
    return make() if history == 1 else SerialEnv(1, make)


def newest_frame(trajectory: TensorDictBase) -> TensorDictBase:
    """Keeps only the newest frame of history-stacked observations (root and ``"next"``)."""
    out = trajectory.clone(False)
    for key, frame_dim in ((keys.POINT_CLOUD, -3), (keys.AGENT_POS, -2)):
        for nested in (key, ("next", key)):
            if nested in out.keys(include_nested=True):
                value = out.get(nested)
                if value.dim() - trajectory.batch_dims == (3 if key == keys.POINT_CLOUD else 2):
                    out.set(nested, value.select(frame_dim, -1))
    return out


class EpisodeSeeded(TensorDictModuleBase):
    """A collection worker's policy: at every episode start (``is_init``) it restarts the policy's random stream
    (its ``reset(seed + POLICY_SEED_OFFSET)``, if it has one) and its drift noise's from the episode's seed,
    which the env writes (``make_env(..., seed_stride=k)``), so an episode's actions depend on that seed only."""

    def __init__(self, policy: Callable, noise: DriftNoise | None = None):
        super().__init__()
        self.policy, self.noise = policy, noise
        self.in_keys = [*getattr(policy, "in_keys", []), keys.IS_INIT, keys.EPISODE_SEED]
        self.out_keys = list(getattr(policy, "out_keys", [keys.ACTION]))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.get(keys.IS_INIT).any():
            seed = int(tensordict.get(keys.EPISODE_SEED).reshape(-1)[0])  # a worker steps one env
            if callable(getattr(self.policy, "reset", None)):
                self.policy.reset(seed + POLICY_SEED_OFFSET)
            if self.noise is not None:
                self.noise.reset(seed)
        tensordict = self.policy(tensordict)
        return self.noise(tensordict) if self.noise is not None else tensordict


def _source_policy(task: TaskSpec, source: Source, noise_correlation: float) -> EpisodeSeeded:
    """The policy of ``source`` with its drift noise, both seeded per episode (one call per worker)."""
    policy = source.policy() if source.policy is not None else make_expert(task)
    noise = DriftNoise(source.noise_scale, correlation=noise_correlation) if source.noise_scale > 0 else None
    return EpisodeSeeded(policy, noise)


def split_episodes(pieces: dict[int, list[TensorDictBase]], batch: TensorDictBase) -> dict[int, TensorDictBase]:
    """Appends the steps of a collector's batch (any shape, from any of its workers) to the unfinished episodes
    in ``pieces`` (by episode seed, in place) and returns the episodes that ended in it, by seed."""
    batch = batch.reshape(-1)
    seeds = batch[keys.EPISODE_SEED].reshape(-1)
    done = batch["next", keys.DONE].reshape(-1)
    completed = {}
    for seed in dict.fromkeys(seeds.tolist()):  # a worker's steps are in time order
        steps = seeds == seed
        pieces.setdefault(seed, []).append(batch[steps])
        if done[steps][-1]:
            completed[seed] = torch.cat(pieces.pop(seed))
    return completed


def _check_ray_cpus(ray, workers: int) -> None:
    """Refuses more collector actors than the Ray cluster has CPUs: the actors left over would wait forever."""
    cpus = ray.cluster_resources().get("CPU", 0)
    if cpus < workers * RAY_ACTOR_RESOURCES["num_cpus"]:
        raise ValueError(
            f"the Ray cluster has {cpus:g} CPUs, fewer than num_workers={workers} collector actors of one CPU each "
            f"would need: lower num_workers, or start Ray with more (ray_init_config={{'num_cpus': {workers}}})"
        )


def _make_collector(backend: str, env_fns: list[Callable], policy_fn: Callable, ray_init_config: dict | None):
    """One TorchRL collector whose ``len(env_fns)`` workers each step one env and one policy, gathered
    ``FRAMES_PER_WORKER`` steps per worker at a time."""
    workers = len(env_fns)
    frames = FRAMES_PER_WORKER * workers
    if backend == "ray":
        from torchrl.collectors.distributed import RayCollector

        return RayCollector(
            env_fns,
            policy_factory=[policy_fn] * workers,
            frames_per_batch=frames,
            total_frames=sys.maxsize,  # -1 stops it at once
            collector_class=Collector,
            sync=True,
            num_collectors=workers,
            ray_init_config=ray_init_config,
            remote_configs=RAY_ACTOR_RESOURCES,
        )
    if workers > 1:  # env and policy step in each worker process; this process only gathers
        return MultiSyncCollector(
            env_fns, policy_factory=[policy_fn] * workers, frames_per_batch=frames, total_frames=-1, cat_results="stack"
        )
    return Collector(env_fns[0](), policy_fn(), frames_per_batch=frames, total_frames=-1)


def collect(
    task: str | TaskSpec,
    root: str | Path,
    sources: list[Source],
    *,
    seed: int = 0,
    gamma: float = 0.99,
    num_points: int = 512,
    num_workers: int = 2,
    chunk_size: int = 50,
    successes_only: bool = False,
    noise_correlation: float = 0.9,
    max_failures: int | None = None,
    progress: bool = True,
    backend: str = "local",
    ray_init_config: dict | None = None,
) -> TrajectoryDataset:
    """Collects labeled trajectories of ``task`` into the dataset directory ``root``.

    A complete dataset with the same configuration is loaded, not collected again; an unfinished
    one is resumed.

    Args:
        task: the task name (or a :class:`~torchrl_dalir.envs.TaskSpec`).
        root: the dataset directory.
        sources: the policies to roll out, with their noise and trajectory counts.
        seed: the dataset's data-generation seed (env and noise seeds derive from it).
        gamma: discount of the completion targets.
        num_points: points per cloud.
        num_workers: collector workers (env processes, or Ray actors); the data do not depend on it.
        chunk_size: trajectories per stored chunk (the unit of resumption).
        successes_only: keep only successful trajectories (expert demos); failed attempts are
            dropped and counted in ``meta.json``.
        noise_correlation: lag-1 correlation of the drift noise.
        max_failures: with ``successes_only``, give up after this many failures in one chunk
            (default: 10 times the chunk's size).
        progress: show a progress bar.
        backend: ``"local"``, worker processes on this machine (TorchRL's ``MultiSyncCollector``), or
            ``"ray"``, Ray actors (TorchRL's ``RayCollector``; ``pip install "torchrl_dalir[ray]"``); the data
            do not depend on it.
        ray_init_config: with ``backend="ray"`` and Ray not yet initialized in this process, the keywords of
            the ``ray.init`` that starts it (``{"address": "auto"}`` joins a running cluster; by default a
            local instance starts, or the cluster that ``RAY_ADDRESS`` names is joined); it is shut down at the end.

    Example:
        >>> from torchrl_dalir.data import Source, collect
        >>> demos = collect("disassemble", "data/demos", [Source("expert", 10)], successes_only=True)  # doctest: +SKIP
    """
    spec = get_task(task)
    check_choice("backend", backend, BACKENDS)
    check_at_least("num_workers", num_workers, 1)
    check_at_least("chunk_size", chunk_size, 1)
    if not sources or any(s.num_trajectories < 0 for s in sources):
        raise ValueError("give at least one source, each with a non-negative number of trajectories")
    check_data_seed(seed * SEEDS_PER_DATASET)
    root = Path(root)
    meta = DatasetMeta(
        task=spec.name, num_points=num_points, gamma=gamma, seed=seed, sources=[s.describe() for s in sources]
    )
    writer = DatasetWriter(root, meta)
    if writer.meta.complete:
        return TrajectoryDataset.load(root)

    chunks = []  # (chunk index, source index, number of trajectories)
    for source_index, source in enumerate(sources):
        for start in range(0, source.num_trajectories, chunk_size):
            chunks.append((len(chunks), source_index, min(chunk_size, source.num_trajectories - start)))
    if len(chunks) * SEEDS_PER_CHUNK > SEEDS_PER_DATASET:
        raise ValueError(f"too many chunks ({len(chunks)}); raise chunk_size")
    todo = [c for c in chunks if c[0] not in writer.done_chunks()]

    total = sum(s.num_trajectories for s in sources)
    cfg = dict(
        num_workers=num_workers,
        num_points=num_points,
        noise_correlation=noise_correlation,
        gamma=gamma,
        successes_only=successes_only,
        backend=backend,
        ray_init_config=ray_init_config,
    )
    # one Ray runtime for every chunk (each chunk's collector would start and stop its own)
    runtime = ray_runtime('backend="ray"', ray_init_config) if backend == "ray" and todo else nullcontext()
    with runtime as ray:
        if ray is not None:
            _check_ray_cpus(ray, num_workers)
        with tqdm(
            total=total,
            initial=writer.meta.num_trajectories,
            desc=f"collect {spec.name}",
            unit="traj",
            disable=not progress,
        ) as bar:
            for chunk, source_index, count in todo:
                chunk_seed = check_data_seed(seed * SEEDS_PER_DATASET + chunk * SEEDS_PER_CHUNK)
                cfg["max_failures"] = max_failures if max_failures is not None else 10 * count
                rows, info = _collect_chunk(spec, sources[source_index], source_index, count, chunk_seed, cfg, bar)
                writer.write_chunk(chunk, rows, source=sources[source_index].name, seed=chunk_seed, **info)
    return writer.finalize()


def _collect_chunk(spec, source, source_index, count, chunk_seed, cfg, bar):
    """Collects ``count`` kept trajectories of one source: attempt ``i`` resets with ``chunk_seed + i`` (worker
    ``w`` of ``W`` runs attempts ``w, w + W, ...``) and attempts are kept in seed order, so a chunk is the same
    whenever, wherever and by however many workers it is collected."""
    workers = cfg["num_workers"]
    low, high = action_bounds(spec)
    env_fns = [
        partial(_worker_env, spec, chunk_seed + w, workers, cfg["num_points"], source.history) for w in range(workers)
    ]
    policy_fn = partial(_source_policy, spec, source, cfg["noise_correlation"])
    threads = torch.get_num_threads()  # TorchRL's multi-process collector changes it; the caller's choice stands
    kept, reset_seeds, failures, steps, attempt = [], [], 0, 0, 0
    pieces, finished = {}, {}  # unfinished and finished episodes, by seed
    collector = None
    try:
        with warnings.catch_warnings():  # the workers build their own policies: RayCollector has no weights to sync
            warnings.filterwarnings("ignore", message=".*(not an nn.Module|before weight synchronization)")
            collector = _make_collector(cfg["backend"], env_fns, policy_fn, cfg["ray_init_config"])
            start = time.perf_counter()
            for batch in collector:
                finished.update(split_episodes(pieces, batch))
                while chunk_seed + attempt in finished and len(kept) < count:
                    episode_seed = chunk_seed + attempt
                    attempt += 1
                    trajectory = newest_frame(finished.pop(episode_seed))
                    trajectory[keys.ACTION] = trajectory[keys.ACTION].clamp(low, high)  # what the simulator executed
                    steps += len(trajectory)
                    rows = trajectory_rows(
                        trajectory,
                        trajectory_id=len(kept),
                        source=source_index,
                        noise_scale=source.noise_scale,
                        expert_source=source.expert and source.noise_scale == 0,
                        gamma=cfg["gamma"],
                    )
                    if cfg["successes_only"] and rows[keys.TERMINAL_LABEL][0] < 1:
                        failures += 1
                        if failures > cfg["max_failures"]:
                            raise RuntimeError(
                                f"{failures} failed attempts while collecting {count} successes from {source.name!r}"
                            )
                        continue
                    kept.append(rows)
                    reset_seeds.append(episode_seed)
                    bar.update(1)
                if len(kept) == count:
                    break
                if attempt >= SEEDS_PER_CHUNK:
                    raise RuntimeError(
                        f"{count} trajectories from {source.name!r} took more than {SEEDS_PER_CHUNK} attempts "
                        "in one chunk: lower chunk_size"
                    )
    finally:
        if collector is not None:
            collector.shutdown()
        torch.set_num_threads(threads)
    seconds = time.perf_counter() - start
    info = {"failures_dropped": failures, "env_steps": steps, "seconds": round(seconds, 2), "reset_seeds": reset_seeds}
    return torch.cat(kept), info
