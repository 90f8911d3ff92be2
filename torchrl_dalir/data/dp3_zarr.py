"""DP3's zarr datasets (its real-robot releases) as the library's trajectory datasets.

3D Diffusion Policy stores a dataset as one zarr group, every step of every episode in a row::

    data/point_cloud   [S, N, C]  xyz (C = 3) or xyz + rgb (C = 6), in the robot's frame
    data/state         [S, D]     the robot's proprioception
    data/action        [S, A]     the action taken at the step
    meta/episode_ends  [E]        the end (exclusive) of every episode: cumulative step counts

(other arrays, such as ``data/img`` or ``data/depth``, are ignored). :func:`import_dp3_zarr`
writes such a store as a :class:`~torchrl_dalir.data.TrajectoryDataset`, through the same labeled
rows and resumable, atomic writer as a collection: an episode of ``L`` steps becomes a trajectory
of ``T = L - 1`` actions (rows ``s_0 .. s_{L-1}``); its last action, whose outcome was never
observed, is dropped. Clouds keep xyz (colour is dropped, as the policies read xyz only) and are
farthest-point sampled to ``num_points``. The released episodes carry no outcome: they are
demonstrations, so each is labeled a success (``terminal_label`` 1, ``quality`` ``expert``,
``completion_target`` ``gamma^(T - t)``, i.e. progress along the demo), and ``meta.json`` says that
the label is assumed. They carry no reward either, so the rows have no ``reward`` column.

:func:`write_dp3_zarr` writes episodes in DP3's layout (zarr format 2, as DP3 writes): the tests'
stores and the made store of ``examples/paper/table4_real_world.py``.

Reading needs the ``zarr`` package (``pip install 'torchrl_dalir[real]'``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from torchrl_dalir import keys
from torchrl_dalir.data.labels import trajectory_rows
from torchrl_dalir.data.storage import DatasetMeta, DatasetWriter, TrajectoryDataset
from torchrl_dalir.envs.point_cloud import farthest_point_sample

# Where DP3 keeps each array in its store.
POINT_CLOUD, STATE, ACTION, EPISODE_ENDS = "data/point_cloud", "data/state", "data/action", "meta/episode_ends"
XYZ = 3  # the leading channels of a cloud that are kept
SOURCE_NAME = "dp3_demos"
ASSUMED_LABEL = "assumed: DP3's released episodes are demonstrations, each labeled a success (y_T = 1)"


def _zarr():
    try:
        import zarr
    except ImportError:
        raise ImportError(
            "reading and writing DP3's zarr stores needs the zarr package: pip install 'torchrl_dalir[real]'"
        ) from None
    return zarr


def _open_store(store_path: Path):
    """The store's four arrays (lazy zarr arrays) and its episode ends, checked for presence and shape."""
    if not store_path.exists():
        raise FileNotFoundError(f"no DP3 zarr store at {store_path}")
    try:
        root = _zarr().open_group(str(store_path), mode="r")
    except Exception as error:  # zarr raises several kinds for a folder that is not a store
        raise ValueError(f"{store_path} is not a zarr store ({type(error).__name__}: {error})") from None
    missing = [name for name in (POINT_CLOUD, STATE, ACTION, EPISODE_ENDS) if name not in root]
    if missing:
        raise ValueError(
            f"{store_path} is not in DP3's layout: it has no {', '.join(missing)} "
            f"(DP3 stores {POINT_CLOUD}, {STATE}, {ACTION} and {EPISODE_ENDS})"
        )
    cloud, state, action = root[POINT_CLOUD], root[STATE], root[ACTION]
    if cloud.ndim != 3 or cloud.shape[-1] < XYZ or cloud.shape[1] == 0:
        raise ValueError(
            f"{store_path}/{POINT_CLOUD} must be [steps, points, 3 or 6] (xyz, then any colour), got {cloud.shape}"
        )
    for name, array in ((STATE, state), (ACTION, action)):
        if array.ndim != 2 or array.shape[0] != cloud.shape[0]:
            raise ValueError(
                f"{store_path}/{name} must be [{cloud.shape[0]}, dim] (one row per step, as {POINT_CLOUD}), "
                f"got {array.shape}"
            )
    ends = np.asarray(root[EPISODE_ENDS][:])
    if ends.ndim != 1 or len(ends) == 0 or not np.issubdtype(ends.dtype, np.integer):
        raise ValueError(
            f"{store_path}/{EPISODE_ENDS} must be a non-empty 1-D integer array, got {ends.dtype} {ends.shape}"
        )
    lengths = np.diff(ends, prepend=0)
    if ends[-1] != cloud.shape[0] or (lengths < 2).any():
        short = np.flatnonzero(lengths < 2).tolist()
        raise ValueError(
            f"{store_path}/{EPISODE_ENDS} must rise by at least 2 steps per episode (an action and its outcome) and "
            f"end at {cloud.shape[0]}, the number of steps; got {ends.tolist()}"
            + (f" (episodes {short} are too short)" if short else "")
        )
    return cloud, state, action, ends


def _read(array, steps: slice, name: str, episode: int, store_path: Path, channels: int | None = None) -> np.ndarray:
    """``array[steps]`` (its first ``channels`` channels) as float32, refused if it holds NaN or infinite values."""
    value = np.asarray(array[steps])[..., :channels].astype(np.float32)
    if not np.isfinite(value).all():
        raise ValueError(
            f"{store_path}/{name} holds {int((~np.isfinite(value)).sum())} NaN or infinite values in episode {episode}"
        )
    return value


def _episode_rows(cloud: torch.Tensor, state: torch.Tensor, action: torch.Tensor, gamma: float) -> TensorDict:
    """The labeled rows of one episode of ``L`` steps: its first ``L - 1`` actions, each with the observation
    that followed it, as a successful TorchRL trajectory (see :func:`trajectory_rows`)."""
    steps = len(state) - 1
    end = torch.arange(steps).unsqueeze(-1) == steps - 1
    trajectory = TensorDict(
        {
            keys.POINT_CLOUD: cloud[:-1],
            keys.AGENT_POS: state[:-1],
            keys.ACTION: action[:-1],
            "next": {
                keys.POINT_CLOUD: cloud[1:],
                keys.AGENT_POS: state[1:],
                keys.REWARD: torch.zeros(steps, 1),
                keys.SUCCESS: end,
                keys.DONE: end,
            },
        },
        batch_size=[steps],
    )
    rows = trajectory_rows(trajectory, trajectory_id=0, source=0, noise_scale=0.0, expert_source=True, gamma=gamma)
    return rows.exclude(keys.REWARD)  # DP3 records no reward: no column rather than zeros


def import_dp3_zarr(
    store_path: str | Path,
    out_dir: str | Path,
    *,
    task: str | None = None,
    num_points: int | None = 512,
    gamma: float = 0.99,
    chunk_size: int = 50,
    progress: bool = False,
) -> TrajectoryDataset:
    """Writes the DP3 zarr store ``store_path`` as a trajectory dataset in ``out_dir``.

    Episodes are written in chunks of ``chunk_size``, each atomically: an interrupted import resumes
    where it stopped, and ``out_dir`` loads only once complete (a complete one is loaded, not written
    again). A store with a missing array, arrays of the wrong shape or inconsistent lengths, an
    episode shorter than 2 steps, or NaN or infinite values is refused, naming the array (and episode).

    Args:
        store_path: the ``.zarr`` folder.
        out_dir: the dataset directory to write.
        task: the name stored as the dataset's task (default: the store's folder name without ``.zarr``).
        num_points: points per cloud, farthest-point sampled (a smaller cloud repeats points);
            ``None`` keeps the store's.
        gamma: discount of the completion targets.
        chunk_size: episodes per atomically written chunk.
        progress: show a progress bar.

    Example:
        >>> import tempfile
        >>> import numpy as np
        >>> folder = Path(tempfile.mkdtemp())
        >>> episode = {
        ...     "point_cloud": np.random.rand(5, 100, 6), "state": np.random.rand(5, 7), "action": np.random.rand(5, 7)
        ... }
        >>> store = write_dp3_zarr(folder / "example.zarr", [episode, episode])
        >>> dataset = import_dp3_zarr(store, folder / "dataset", num_points=64)
        >>> dataset.num_trajectories, len(dataset.rows), dataset.rows["point_cloud"].shape[1:]
        (2, 10, torch.Size([64, 3]))
    """
    store_path = Path(store_path)
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be at least 1, got {chunk_size}")
    cloud, state, action, ends = _open_store(store_path)
    kept_points = num_points if num_points is not None else cloud.shape[1]
    if kept_points < 1:
        raise ValueError(f"num_points must be at least 1 (or None), got {num_points}")
    source = {
        "name": SOURCE_NAME,
        "noise_scale": 0.0,
        "expert": True,
        "num_trajectories": len(ends),
        "store": str(store_path.resolve()),
        "terminal_label": ASSUMED_LABEL,
    }
    meta = DatasetMeta(
        task=task or store_path.name.removesuffix(".zarr"),
        num_points=kept_points,
        gamma=gamma,
        seed=0,
        sources=[source],
    )
    writer = DatasetWriter(out_dir, meta)
    if writer.meta.complete:
        return TrajectoryDataset.load(out_dir)
    starts = np.concatenate([[0], ends[:-1]])
    with tqdm(total=len(ends), desc=f"import {meta.task}", unit="episode", disable=not progress) as bar:
        for chunk, first in enumerate(range(0, len(ends), chunk_size)):
            episodes = range(first, min(first + chunk_size, len(ends)))
            if chunk in writer.done_chunks():
                bar.update(len(episodes))
                continue
            rows = []
            for episode in episodes:
                steps = slice(int(starts[episode]), int(ends[episode]))
                xyz = _read(cloud, steps, POINT_CLOUD, episode, store_path, channels=XYZ)
                if num_points is not None:
                    xyz = np.stack([farthest_point_sample(frame, num_points) for frame in xyz])
                observed = [
                    _read(array, steps, name, episode, store_path) for array, name in ((state, STATE), (action, ACTION))
                ]
                rows.append(_episode_rows(*map(torch.from_numpy, (xyz, *observed)), gamma))
                bar.update(1)
            writer.write_chunk(chunk, torch.cat(rows), episodes=[episodes.start, episodes.stop])
    return writer.finalize()


def write_dp3_zarr(store_path: str | Path, episodes: list[dict[str, np.ndarray]]) -> Path:
    """Writes ``episodes`` as a zarr store in DP3's layout (zarr format 2, float32 arrays, as DP3 writes it).

    Args:
        store_path: the ``.zarr`` folder (replaced if it exists).
        episodes: one dict per episode with ``point_cloud`` ``[L, N, C]``, ``state`` ``[L, D]`` and
            ``action`` ``[L, A]`` (numpy arrays, the same ``N, C, D, A`` for every episode).

    Example:
        >>> import tempfile
        >>> import numpy as np
        >>> episode = {"point_cloud": np.zeros((4, 10, 6)), "state": np.zeros((4, 2)), "action": np.zeros((4, 2))}
        >>> write_dp3_zarr(Path(tempfile.mkdtemp()) / "doc_layout.zarr", [episode]).name
        'doc_layout.zarr'
    """
    if not episodes:
        raise ValueError(
            f"write_dp3_zarr({str(store_path)!r}, []): no episode to write (a DP3 store holds at least one)"
        )
    zarr = _zarr()
    fmt = {"zarr_format": 2} if int(zarr.__version__.split(".")[0]) >= 3 else {}  # zarr 2 writes format 2 by default
    root = zarr.open_group(str(store_path), mode="w", **fmt)
    for name in (POINT_CLOUD, STATE, ACTION):
        root[name] = np.concatenate([np.asarray(e[name.rpartition("/")[2]], dtype=np.float32) for e in episodes])
    root[EPISODE_ENDS] = np.cumsum([len(e["state"]) for e in episodes]).astype(np.int64)
    return Path(store_path)
