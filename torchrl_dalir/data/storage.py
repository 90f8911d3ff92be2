"""Labeled trajectories on disk: memory-mapped TensorDicts behind a TorchRL replay buffer.

A dataset is a directory::

    meta.json        what it holds (task, shapes, gamma, sources, shards) and whether it is complete
    shards/00003/    one memory-mapped TensorDict per collection chunk, while collecting
    rows/            all rows in one memory-mapped TensorDict, once complete

Every shard and ``rows/`` is written under a temporary name and renamed into place, and
``meta.json`` is replaced atomically after each, so a crash leaves a dataset that resumes from
its last finished chunk and never one that loads as complete: a dataset is complete only once
``meta.json`` says so (:func:`is_complete`). Loading checks every column file against the stored
shapes and maps it read-only, so a damaged dataset is refused with the damaged file named and
is never modified.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.data import ReplayBuffer, TensorStorage

from torchrl_dalir import keys
from torchrl_dalir.utils import atomic_write

FORMAT_VERSION = 1
# every episode resets with a seed of its own; "worker" (meta.json without the field): one stream per worker
SEEDING = "episode"


@dataclass
class DatasetMeta:
    """The contents of ``meta.json``.

    Example:
        >>> meta = DatasetMeta("reach", num_points=64, gamma=0.99, seed=0, sources=[])
        >>> meta.shards = [{"chunk": 0, "num_trajectories": 2, "num_rows": 150},
        ...                {"chunk": 1, "num_trajectories": 1, "num_rows": 81}]
        >>> meta.num_trajectories, meta.num_rows, meta.complete
        (3, 231, False)
    """

    task: str
    num_points: int
    gamma: float
    seed: int
    sources: list[dict]  # one per source: name, noise_scale, expert, num_trajectories
    shards: list[dict] = field(default_factory=list)  # one per finished chunk
    complete: bool = False
    format_version: int = FORMAT_VERSION
    library_version: str = ""
    seeding: str = SEEDING

    @property
    def num_trajectories(self) -> int:
        return sum(s["num_trajectories"] for s in self.shards)

    @property
    def num_rows(self) -> int:
        return sum(s["num_rows"] for s in self.shards)

    def plan(self) -> dict:
        """The fields that must match for a collection to resume into this directory."""
        return {k: getattr(self, k) for k in ("task", "num_points", "gamma", "seed", "sources", "format_version")}


def _read_json(path: Path) -> dict:
    """The JSON object in ``path``; a half-written or invalid file is refused with its path."""
    try:
        content = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(
            f"{path} is damaged (not valid JSON: {error}); delete its dataset directory and collect it again"
        ) from None
    if not isinstance(content, dict):
        raise ValueError(
            f"{path} is damaged (holds a {type(content).__name__}, not a JSON object); "
            "delete its dataset directory and collect it again"
        )
    return content


def _read_meta(root: Path) -> DatasetMeta:
    path = root / "meta.json"
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {root}: {path} is missing")
    content = _read_json(path)
    content.setdefault("seeding", "worker")  # written before the field
    try:
        return DatasetMeta(**content)
    except TypeError as error:
        raise ValueError(f"{path} is not a dataset's meta.json ({error}); delete {root} and collect it again") from None


def is_complete(root: str | Path) -> bool:
    """Whether ``root`` holds a complete dataset (its ``meta.json`` says so): a stage that collects it is done
    only then; an incomplete one is resumed by running the same collection again."""
    root = Path(root)
    return (root / "meta.json").exists() and _read_meta(root).complete


def _open_columns(directory: Path, num_rows: int) -> TensorDict:
    """The columns of a memory-mapped TensorDict directory, each checked against the shape and dtype that its
    ``meta.json`` records (present, ``num_rows`` rows, the file's size) and mapped read-only (copy-on-write), so
    a load never grows or modifies a file."""
    columns = {}
    for key, entry in _read_json(directory / "meta.json").items():
        if not isinstance(entry, dict):  # the batch size, device and type of the TensorDict
            continue
        dtype = getattr(torch, str(entry.get("dtype", "")).removeprefix("torch."), None)
        if not isinstance(dtype, torch.dtype) or "shape" not in entry or entry.get("is_nested") or "type" in entry:
            raise ValueError(
                f"{directory / 'meta.json'} describes {key!r} as {entry}, not a column of this library's datasets"
            )
        shape = torch.Size(entry["shape"])
        path = directory / f"{key}.memmap"
        if not shape or shape[0] != num_rows:
            raise ValueError(f"{path} holds {tuple(shape)} values; its dataset's meta.json records {num_rows} rows")
        if shape.numel() == 0:  # tensordict writes no file for an empty column
            columns[key] = torch.empty(shape, dtype=dtype)
            continue
        if not path.is_file():
            raise FileNotFoundError(
                f"{path} is missing: the dataset is damaged; delete {directory.parent} and collect it again"
            )
        expected, size = shape.numel() * dtype.itemsize, path.stat().st_size
        if size != expected:
            raise ValueError(
                f"{path} has {size} bytes, but its {tuple(shape)} {dtype} column needs {expected} "
                f"(a truncated or damaged file); delete {directory.parent} and collect it again"
            )
        columns[key] = torch.from_file(str(path), shared=False, size=shape.numel(), dtype=dtype).view(shape)
    return TensorDict(columns, batch_size=[num_rows])


def _write_meta(root: Path, meta: DatasetMeta) -> None:
    atomic_write(root / "meta.json", json.dumps(asdict(meta), indent=1))


def _memmap_atomically(rows: TensorDict, directory: Path) -> None:
    tmp = directory.with_name(directory.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    rows.memmap(tmp)
    shutil.rmtree(directory, ignore_errors=True)
    tmp.rename(directory)


class DatasetWriter:
    """Writes a dataset chunk by chunk; re-opening an unfinished directory resumes it.

    Args:
        root: the dataset directory.
        meta: what the dataset will hold; when ``root`` already holds a dataset, its plan must
            match (same task, points, gamma, seed and sources) or opening fails.

    Example:
        >>> import tempfile
        >>> from torchrl_dalir.data import trajectory_rows
        >>> done = torch.tensor([[False], [False], [True]])  # 3 actions, then a success
        >>> episode = TensorDict({"point_cloud": torch.rand(3, 8, 3), "agent_pos": torch.rand(3, 4),
        ...                       "action": torch.rand(3, 4),
        ...                       "next": {"point_cloud": torch.rand(3, 8, 3), "agent_pos": torch.rand(3, 4),
        ...                                "reward": torch.zeros(3, 1), "success": done, "done": done}}, [3])
        >>> meta = DatasetMeta("synthetic", num_points=8, gamma=0.5, seed=0, sources=[])
        >>> writer = DatasetWriter(tempfile.mkdtemp(), meta)
        >>> for chunk in range(2):  # one trajectory per chunk
        ...     rows = trajectory_rows(episode, trajectory_id=0, source=0, noise_scale=0.0, expert_source=True,
        ...                            gamma=0.5)
        ...     writer.write_chunk(chunk, rows)
        >>> dataset = writer.finalize()  # joined, renumbered, marked complete
        >>> (dataset.num_trajectories, dataset.rows["trajectory_id"].tolist(),
        ...  dataset.rows["completion_target"][:4].tolist())
        (2, [0, 0, 0, 0, 1, 1, 1, 1], [0.125, 0.25, 0.5, 1.0])
        >>> TrajectoryDataset.load(writer.root).num_trajectories  # memory-mapped, read-only
        2
    """

    def __init__(self, root: str | Path, meta: DatasetMeta):
        from torchrl_dalir import __version__

        self.root = Path(root)
        meta.library_version = __version__
        if (self.root / "meta.json").exists():
            existing = _read_meta(self.root)
            if existing.plan() != meta.plan():
                raise ValueError(
                    f"{self.root} holds a dataset collected with another configuration:\n"
                    f"  on disk:   {existing.plan()}\n  requested: {meta.plan()}\n"
                    "choose another directory, or delete this one to start over"
                )
            if not existing.complete and existing.seeding != meta.seeding:
                raise ValueError(
                    f"{self.root} was partly collected by an older version of the library, which seeded each worker, "
                    "not each episode: resuming would mix the two; delete it to collect it again"
                )
            self.meta = existing
            if existing.complete:  # finishes a finalize interrupted after the complete mark
                shutil.rmtree(self.root / "shards", ignore_errors=True)
        else:
            self.root.mkdir(parents=True, exist_ok=True)
            self.meta = meta
            _write_meta(self.root, meta)

    def done_chunks(self) -> set[int]:
        return {s["chunk"] for s in self.meta.shards}

    def write_chunk(self, chunk: int, rows: TensorDict, **info) -> None:
        """Stores a finished chunk's rows and records it (``info`` goes into the shard entry)."""
        _memmap_atomically(rows, self.root / "shards" / f"{chunk:05d}")
        num_trajectories = int(rows[keys.IS_FINAL].sum())
        self.meta.shards.append({"chunk": chunk, "num_trajectories": num_trajectories, "num_rows": len(rows), **info})
        _write_meta(self.root, self.meta)

    def finalize(self) -> TrajectoryDataset:
        """Joins the shards into ``rows/`` in chunk order, renumbers trajectories, marks complete."""
        shards = sorted(self.meta.shards, key=lambda s: s["chunk"])
        rows = torch.cat([_open_columns(self.root / "shards" / f"{s['chunk']:05d}", s["num_rows"]) for s in shards])
        rows[keys.TRAJECTORY_ID] = torch.cumsum(rows[keys.STEP] == 0, 0) - 1
        _memmap_atomically(rows, self.root / "rows")
        self.meta.shards = shards
        self.meta.complete = True
        _write_meta(self.root, self.meta)
        shutil.rmtree(self.root / "shards", ignore_errors=True)
        return TrajectoryDataset.load(self.root)


class TrajectoryDataset:
    """A complete dataset of labeled trajectories, memory-mapped from disk.

    ``rows`` holds one row per observation (see :mod:`torchrl_dalir.data.labels`);
    :meth:`replay_buffer` serves them through a TorchRL replay buffer without copying.

    Example:
        >>> from torchrl_dalir.data import trajectory_rows
        >>> timed_out = torch.tensor([[False], [True]])  # 2 actions, then the step limit
        >>> episode = TensorDict({"agent_pos": torch.rand(2, 4), "action": torch.rand(2, 4), "next": {
        ...     "agent_pos": torch.rand(2, 4), "reward": torch.zeros(2, 1),
        ...     "success": torch.zeros(2, 1, dtype=torch.bool), "done": timed_out}}, [2])
        >>> rows = trajectory_rows(episode, trajectory_id=0, source=0, noise_scale=0.0, expert_source=True, gamma=0.9)
        >>> meta = DatasetMeta("synthetic", 8, 0.9, 0, [])
        >>> dataset = TrajectoryDataset(Path("in-memory"), meta, rows)  # load() maps one from disk
        >>> dataset.num_trajectories, len(dataset.trajectory(0)), dataset.quality_counts()
        (1, 3, {'expert': 0, 'imperfect_success': 0, 'failed': 1})
        >>> dataset.replay_buffer(batch_size=4).sample()["terminal_label"]
        tensor([0., 0., 0., 0.])
    """

    def __init__(self, root: Path, meta: DatasetMeta, rows: TensorDict):
        self.root = root
        self.meta = meta
        self.rows = rows
        is_start = rows[keys.STEP] == 0
        self.starts = torch.nonzero(is_start).squeeze(-1)
        self.lengths = torch.diff(self.starts, append=torch.tensor([len(rows)]))  # rows per trajectory (T + 1)

    @classmethod
    def load(cls, root: str | Path, *, task: str | None = None, num_points: int | None = None) -> TrajectoryDataset:
        """Loads a complete dataset; refuses an unfinished or damaged one (naming the damaged file), or one of
        another task or shape. Nothing on disk is modified."""
        root = Path(root)
        meta = _read_meta(root)
        if not meta.complete:
            raise RuntimeError(
                f"the dataset at {root} is incomplete ({len(meta.shards)} chunks written): "
                "run the same collection again to resume it"
            )
        if meta.format_version != FORMAT_VERSION:
            raise ValueError(f"{root} has dataset format {meta.format_version}; this library reads {FORMAT_VERSION}")
        if task is not None and meta.task != task:
            raise ValueError(f"the dataset at {root} is for task {meta.task!r}, not {task!r}")
        if num_points is not None and meta.num_points != num_points:
            raise ValueError(f"the dataset at {root} has {meta.num_points} points per cloud, not {num_points}")
        rows = _open_columns(root / "rows", meta.num_rows)
        if keys.POINT_CLOUD in rows.keys() and rows[keys.POINT_CLOUD].shape[-2:] != (meta.num_points, 3):
            raise ValueError(
                f"{root}: point clouds of shape {tuple(rows[keys.POINT_CLOUD].shape[-2:])} contradict meta.json"
            )
        return cls(root, meta, rows)

    @classmethod
    def concat(cls, datasets: list[TrajectoryDataset]) -> TrajectoryDataset:
        """One in-memory dataset holding every trajectory of ``datasets`` (same task and cloud
        size), in order, renumbered; its meta lists every source. ``root`` is the first one's."""
        first = datasets[0]
        for other in datasets[1:]:
            if (other.meta.task, other.meta.num_points, other.meta.gamma) != (
                first.meta.task,
                first.meta.num_points,
                first.meta.gamma,
            ):
                raise ValueError(
                    f"cannot join {other.root} "
                    f"({other.meta.task}, {other.meta.num_points} points, gamma {other.meta.gamma}) "
                    f"to {first.root} ({first.meta.task}, {first.meta.num_points} points, gamma {first.meta.gamma})"
                )
        common = set.intersection(*(set(d.rows.keys(include_nested=True, leaves_only=True)) for d in datasets))
        rows = torch.cat([d.rows.select(*common).to_tensordict() for d in datasets])
        sources, offset = [], 0
        for d in datasets:  # source indices continue across datasets
            rows[keys.SOURCE][offset : offset + len(d.rows)] += len(sources)
            sources += d.meta.sources
            offset += len(d.rows)
        rows[keys.TRAJECTORY_ID] = torch.cumsum(rows[keys.STEP] == 0, 0) - 1
        meta = dataclasses.replace(first.meta, sources=sources, shards=[s for d in datasets for s in d.meta.shards])
        return cls(first.root, meta, rows)

    @property
    def task(self) -> str:
        return self.meta.task

    @property
    def num_trajectories(self) -> int:
        return len(self.starts)

    def trajectory(self, index: int) -> TensorDict:
        """The ``T + 1`` rows of trajectory ``index``."""
        start = int(self.starts[index])
        return self.rows[start : start + int(self.lengths[index])]

    def terminal_labels(self) -> torch.Tensor:
        return self.rows[keys.TERMINAL_LABEL][self.starts]

    def quality_counts(self) -> dict[str, int]:
        quality = self.rows[keys.QUALITY][self.starts]
        return {tag: int((quality == i).sum()) for i, tag in enumerate(keys.QUALITY_TAGS)}

    def replay_buffer(self, batch_size: int | None = None, sampler=None) -> ReplayBuffer:
        """A TorchRL replay buffer over the memory-mapped rows (no copy)."""
        return ReplayBuffer(storage=TensorStorage(self.rows), sampler=sampler, batch_size=batch_size)

    def __repr__(self) -> str:
        return (
            f"TrajectoryDataset(task={self.task!r}, trajectories={self.num_trajectories}, rows={len(self.rows)}, "
            f"quality={self.quality_counts()}, root={str(self.root)!r})"
        )
