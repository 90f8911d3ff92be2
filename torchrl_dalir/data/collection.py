"""Collecting labeled trajectories with TorchRL collectors into an on-disk dataset.

A collection is a list of :class:`Source`\\ s (a policy, a drift-noise scale, a number of
trajectories). Each source is split into chunks; a chunk is collected by a TorchRL
``MultiSyncCollector`` whose workers each step one env and one copy of the policy (rendering
and acting stay in the worker; this process only gathers), and is stored as soon as it is
finished, so an interrupted collection resumes at its first unfinished chunk and gives the
same data as an uninterrupted one: every random stream of a chunk (env, drift noise, the
policy's sampling) is seeded from the chunk's seed, never taken from the process's state.
Stored actions are the executed ones, clipped to the env's action bounds.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import SerialEnv
from tqdm.auto import tqdm

from torchrl_dalir import keys
from torchrl_dalir.data.labels import trajectory_rows
from torchrl_dalir.data.storage import DatasetMeta, DatasetWriter, TrajectoryDataset
from torchrl_dalir.envs import TaskSpec, action_bounds, get_task, make_env
from torchrl_dalir.experts import add_drift_noise, make_expert
from torchrl_dalir.seeds import check_data_seed

SEEDS_PER_DATASET = 1_000_000  # chunk c of dataset seed s seeds its envs with s * 1e6 + c * 1e3 (+ worker)
SEEDS_PER_CHUNK = 1_000
FRAMES_PER_WORKER = 64  # env steps per worker between two gathers
POLICY_SEED_OFFSET = 1 << 40  # a worker's policy samples from its seed + this: a stream apart from its drift noise's


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
            per chunk and worker; any other one must not draw from torch's global generator.
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
        return {"name": self.name, "num_trajectories": self.num_trajectories, "noise_scale": self.noise_scale, "expert": self.expert}


def _worker_env(task: TaskSpec, seed: int, num_points: int, history: int):
    if history == 1:
        return make_env(task, seed=seed, num_points=num_points)
    return SerialEnv(1, partial(make_env, task, seed=seed, num_points=num_points, history=history))


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


def _source_policy(task: TaskSpec, source: Source, noise_correlation: float, seed: int):
    """The policy of ``source``, its sampling noise and its drift noise seeded from ``seed`` (one call
    per worker), so that a chunk does not depend on what ran before it in the process."""
    policy = source.policy() if source.policy is not None else make_expert(task)
    if callable(getattr(policy, "reset", None)):
        policy.reset(seed + POLICY_SEED_OFFSET)
    if source.noise_scale > 0:
        policy = add_drift_noise(policy, source.noise_scale, noise_correlation, seed=seed)
    return policy


def split_completed(pieces: list[TensorDictBase], batch: TensorDictBase) -> list[TensorDictBase]:
    """Appends one worker's ``[frames]`` batch to its unfinished ``pieces`` (in place) and returns
    the trajectories that ended in it."""
    done = batch["next", keys.DONE].reshape(len(batch))
    completed, start = [], 0
    for end in (torch.nonzero(done).squeeze(-1) + 1).tolist():
        pieces.append(batch[start:end])
        completed.append(torch.cat(pieces))
        pieces.clear()
        start = end
    if start < len(batch):
        pieces.append(batch[start:])
    return completed


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
) -> TrajectoryDataset:
    """Collects labeled trajectories of ``task`` into the dataset directory ``root``.

    A complete dataset with the same configuration is loaded, not collected again; an unfinished
    one is resumed.

    Args:
        task: the task name (or a :class:`TaskSpec`).
        root: the dataset directory.
        sources: the policies to roll out, with their noise and trajectory counts.
        seed: the dataset's data-generation seed (env and noise seeds derive from it).
        gamma: discount of the completion targets.
        num_points: points per cloud.
        num_workers: env processes.
        chunk_size: trajectories per stored chunk (the unit of resumption).
        successes_only: keep only successful trajectories (expert demos); failed attempts are
            dropped and counted in ``meta.json``.
        noise_correlation: lag-1 correlation of the drift noise.
        max_failures: with ``successes_only``, give up after this many failures in one chunk
            (default: 10 times the chunk's size).
        progress: show a progress bar.

    Example:
        >>> from torchrl_dalir.data import Source, collect
        >>> demos = collect("disassemble", "data/demos", [Source("expert", 10)], successes_only=True)  # doctest: +SKIP
    """
    spec = get_task(task)
    if not sources or any(s.num_trajectories < 0 for s in sources):
        raise ValueError("give at least one source, each with a non-negative number of trajectories")
    check_data_seed(seed * SEEDS_PER_DATASET)
    root = Path(root)
    meta = DatasetMeta(task=spec.name, num_points=num_points, gamma=gamma, seed=seed, sources=[s.describe() for s in sources])
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
    cfg = dict(num_workers=num_workers, num_points=num_points, noise_correlation=noise_correlation, gamma=gamma, successes_only=successes_only)
    with tqdm(total=total, initial=writer.meta.num_trajectories, desc=f"collect {spec.name}", unit="traj", disable=not progress) as bar:
        for chunk, source_index, count in todo:
            chunk_seed = check_data_seed(seed * SEEDS_PER_DATASET + chunk * SEEDS_PER_CHUNK)
            cfg["max_failures"] = max_failures if max_failures is not None else 10 * count
            rows, info = _collect_chunk(spec, sources[source_index], source_index, count, chunk_seed, cfg, bar)
            writer.write_chunk(chunk, rows, source=sources[source_index].name, seed=chunk_seed, **info)
    return writer.finalize()


def _collect_chunk(spec, source, source_index, count, chunk_seed, cfg, bar):
    """Collects ``count`` kept trajectories of one source; worker ``w`` seeds its env and its
    noise with ``chunk_seed + w``, so a chunk is the same whenever it is collected."""
    workers = cfg["num_workers"]
    low, high = action_bounds(spec)
    env_fns = [partial(_worker_env, spec, chunk_seed + w, cfg["num_points"], source.history) for w in range(workers)]
    policy_fns = [partial(_source_policy, spec, source, cfg["noise_correlation"], chunk_seed + w) for w in range(workers)]
    frames = FRAMES_PER_WORKER * workers
    threads = torch.get_num_threads()  # TorchRL's multi-process collector changes it; the caller's choice stands
    if workers > 1:  # env and policy step in each worker process; this process only gathers
        collector = MultiSyncCollector(env_fns, policy_factory=policy_fns, frames_per_batch=frames, total_frames=-1, cat_results="stack")
    else:
        collector = Collector(env_fns[0](), policy_fns[0](), frames_per_batch=frames, total_frames=-1)
    kept, failures, steps = [], 0, 0
    pieces = [[] for _ in range(workers)]
    start = time.perf_counter()
    try:
        for batch in collector:
            batch = batch.reshape(workers, -1)
            for worker in range(workers):
                for trajectory in split_completed(pieces[worker], batch[worker]):
                    trajectory = newest_frame(trajectory)
                    trajectory[keys.ACTION] = trajectory[keys.ACTION].clamp(low, high)  # what the simulator executed
                    steps += len(trajectory)
                    rows = trajectory_rows(
                        trajectory, trajectory_id=len(kept), source=source_index, noise_scale=source.noise_scale,
                        expert_source=source.expert and source.noise_scale == 0, gamma=cfg["gamma"],
                    )
                    if cfg["successes_only"] and rows[keys.TERMINAL_LABEL][0] < 1:
                        failures += 1
                        if failures > cfg["max_failures"]:
                            raise RuntimeError(f"{failures} failed attempts while collecting {count} successes from {source.name!r}")
                        continue
                    if len(kept) < count:
                        kept.append(rows)
                        bar.update(1)
            if len(kept) == count:
                break
    finally:
        collector.shutdown()
        torch.set_num_threads(threads)
    seconds = time.perf_counter() - start
    return torch.cat(kept), {"failures_dropped": failures, "env_steps": steps, "seconds": round(seconds, 2)}
