import dataclasses
import json
import re
from functools import partial

import pytest
import torch
from conftest import SHORT_REACH, killed_at_source, killed_at_the_complete_mark, still_policy, synthetic_trajectory

from torchrl_dalir import keys
from torchrl_dalir.data import DatasetWriter, Source, TrajectoryDataset, collect, trajectory_rows
from torchrl_dalir.data.storage import DatasetMeta, is_complete
from torchrl_dalir.envs import action_bounds

TINY_REACH = dataclasses.replace(SHORT_REACH, max_steps=16)  # two decisions of the base policy per trajectory


def test_collected_labels_follow_the_formula(collected):
    assert collected.num_trajectories == 5
    gamma = collected.meta.gamma
    for i in range(collected.num_trajectories):
        rows = collected.trajectory(i)
        num_actions = len(rows) - 1
        label = float(rows[keys.SUCCESS][-1])
        assert (rows[keys.TERMINAL_LABEL] == label).all()
        t = torch.arange(num_actions + 1, dtype=torch.float64)
        expected = (gamma ** (num_actions - t) * label).float()
        assert torch.equal(rows[keys.COMPLETION_TARGET].clone(), expected)
        assert torch.equal(rows[keys.STEP].clone(), t.long()) and (rows[keys.TRAJECTORY_ID] == i).all()
        assert rows[keys.IS_FINAL][-1] and not rows[keys.IS_FINAL][:-1].any()
        # a success ends the episode; a failure runs to the step limit
        assert label == 1.0 or num_actions == SHORT_REACH.max_steps


def test_collected_quality_and_sources(collected):
    counts = collected.quality_counts()
    assert counts["expert"] == 2 and counts["failed"] >= 1
    assert sum(counts.values()) == 5
    still = collected.trajectory(4)
    assert collected.meta.sources[int(still[keys.SOURCE][0])]["name"] == "still"
    assert still[keys.TERMINAL_LABEL][0] == 0


def test_dataset_reloads_identical_without_collecting(collected, monkeypatch):
    again = TrajectoryDataset.load(collected.root, task="reach", num_points=64)
    assert (again.rows == collected.rows).all()
    import torchrl_dalir.data.collection as collect_module

    monkeypatch.setattr(collect_module, "_collect_chunk", lambda *a, **k: pytest.fail("collected again"))
    sources = [Source(**{k: v for k, v in s.items()}) for s in collected.meta.sources]
    sources[2].policy = still_policy
    reloaded = collect(
        SHORT_REACH, collected.root, sources, seed=1, gamma=0.9, num_points=64, num_workers=1, chunk_size=2
    )
    assert (reloaded.rows == collected.rows).all()


def test_replay_buffer_serves_the_rows(collected):
    buffer = collected.replay_buffer(batch_size=7)
    assert len(buffer) == len(collected.rows)
    batch = buffer.sample()
    assert batch[keys.POINT_CLOUD].shape == (7, 64, 3)


def test_mismatched_dataset_is_refused(collected):
    with pytest.raises(ValueError, match="task 'reach', not 'disassemble'"):
        TrajectoryDataset.load(collected.root, task="disassemble")
    with pytest.raises(ValueError, match="64 points per cloud, not 512"):
        TrajectoryDataset.load(collected.root, num_points=512)
    with pytest.raises(FileNotFoundError):
        TrajectoryDataset.load(collected.root / "missing")
    with pytest.raises(ValueError, match="another configuration"):
        collect(SHORT_REACH, collected.root, [Source("expert", 3)], seed=1, gamma=0.9, num_points=64)


def crash_after_two_chunks(monkeypatch):
    """Makes the next collection stop (as if killed) when it is about to store its third chunk."""
    original = DatasetWriter.write_chunk

    def write_or_crash(self, chunk, rows, **info):
        if len(self.meta.shards) == 2:
            raise KeyboardInterrupt
        original(self, chunk, rows, **info)

    monkeypatch.setattr(DatasetWriter, "write_chunk", write_or_crash)
    return lambda: monkeypatch.setattr(DatasetWriter, "write_chunk", original)


def test_interrupted_collection_resumes_to_the_same_data(tmp_path, monkeypatch):
    sources = [Source("expert", 2), Source("still", 1, policy=still_policy, expert=False)]
    kwargs = dict(seed=2, gamma=0.9, num_points=32, num_workers=1, chunk_size=1, progress=False)
    reference = collect(SHORT_REACH, tmp_path / "reference", sources, **kwargs)
    restore = crash_after_two_chunks(monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        collect(SHORT_REACH, tmp_path / "resumed", sources, **kwargs)
    meta = json.loads((tmp_path / "resumed" / "meta.json").read_text())
    assert not meta["complete"] and len(meta["shards"]) == 2
    with pytest.raises(RuntimeError, match="incomplete"):
        TrajectoryDataset.load(tmp_path / "resumed")

    restore()
    resumed = collect(SHORT_REACH, tmp_path / "resumed", sources, **kwargs)
    assert (resumed.rows == reference.rows).all()
    assert [s["chunk"] for s in resumed.meta.shards] == [0, 1, 2]


def test_interrupted_base_policy_collection_resumes_to_the_same_data(trained_policy, tmp_path):
    """The sampling noise of the base policy (and of its exploration actor) is seeded per episode, not
    taken from torch's global generator: killed after a chunk and resumed, a collection equals an uninterrupted
    one row by row, whatever state torch's generator is in."""
    from torchrl_dalir.training.policy import exploration_actor, policy_actor

    path = str(trained_policy[1])
    sources = [
        Source("exploration", 1, policy=partial(exploration_actor, path), expert=False, history=2),
        Source("base_policy", 1, policy=partial(policy_actor, path), expert=False, history=2),
    ]
    kwargs = dict(seed=4, num_points=64, num_workers=1, chunk_size=1, progress=False)
    torch.manual_seed(0)
    reference = collect(TINY_REACH, tmp_path / "reference", sources, **kwargs)
    torch.manual_seed(1)
    with killed_at_source(1), pytest.raises(KeyboardInterrupt):
        collect(TINY_REACH, tmp_path / "resumed", sources, **kwargs)
    torch.manual_seed(2)  # the resumed process's global generator is in another state
    resumed = collect(TINY_REACH, tmp_path / "resumed", sources, **kwargs)
    assert (resumed.rows == reference.rows).all()
    assert [s["chunk"] for s in resumed.meta.shards] == [0, 1]
    actions = reference.rows[keys.ACTION]
    low, high = action_bounds(TINY_REACH)
    assert ((actions >= low) & (actions <= high)).all()


class WildPolicy(torch.nn.Module):
    """Writes actions far beyond the bounds, which the env clips to [1, -1, 1, -1]."""

    def forward(self, td):
        return td.set(keys.ACTION, torch.tensor([3.0, -3.0, 1.5, -7.0]).expand(*td.batch_size, 4))


def test_stored_actions_are_the_executed_ones(tmp_path):
    dataset = collect(
        TINY_REACH,
        tmp_path,
        [Source("wild", 1, policy=WildPolicy, expert=False)],
        num_points=32,
        num_workers=1,
        progress=False,
    )
    acting = ~dataset.rows[keys.IS_FINAL]
    assert (dataset.rows[keys.ACTION][acting] == torch.tensor([1.0, -1.0, 1.0, -1.0])).all()


def _synthetic_dataset(root, lengths=(3, 4)):
    """A writer holding synthetic trajectories, one chunk each (no simulator), the same at every call."""
    torch.manual_seed(0)
    writer = DatasetWriter(root, DatasetMeta(task="synthetic", num_points=8, gamma=0.5, seed=0, sources=[]))
    for chunk, length in enumerate(lengths):
        rows = trajectory_rows(
            synthetic_trajectory(length, True),
            trajectory_id=0,
            source=0,
            noise_scale=0.0,
            expert_source=True,
            gamma=0.5,
        )
        writer.write_chunk(chunk, rows)
    return writer


def _sizes(root):
    return {path: path.stat().st_size for path in sorted(root.rglob("*")) if path.is_file()}


@pytest.mark.parametrize(
    "damage", ["truncated column", "deleted column", "half-written meta.json", "invalid rows meta.json"]
)
def test_a_damaged_dataset_is_refused_naming_the_file_and_left_unchanged(tmp_path, damage):
    _synthetic_dataset(tmp_path).finalize()
    column, meta, rows_meta = (
        tmp_path / "rows" / "point_cloud.memmap",
        tmp_path / "meta.json",
        tmp_path / "rows" / "meta.json",
    )
    if damage == "truncated column":
        column.write_bytes(column.read_bytes()[: column.stat().st_size // 2])
        damaged, error = column, ValueError
    elif damage == "deleted column":
        column.unlink()
        damaged, error = column, FileNotFoundError
    elif damage == "half-written meta.json":
        meta.write_text(meta.read_text()[:100])
        damaged, error = meta, ValueError
    else:
        rows_meta.write_text('["not", "a", "tensordict"]')
        damaged, error = rows_meta, ValueError
    sizes = _sizes(tmp_path)
    with pytest.raises(error, match=re.escape(str(damaged))):
        TrajectoryDataset.load(tmp_path)
    assert _sizes(tmp_path) == sizes  # the load grew or rewrote nothing


def test_a_loaded_dataset_is_mapped_read_only(tmp_path):
    dataset = _synthetic_dataset(tmp_path).finalize()
    column = tmp_path / "rows" / "action.memmap"
    before = column.read_bytes()
    dataset.rows[keys.ACTION] += 1  # stays in memory
    assert column.read_bytes() == before and torch.equal(
        TrajectoryDataset.load(tmp_path).rows[keys.ACTION] + 1, dataset.rows[keys.ACTION]
    )


def test_a_crash_before_the_complete_mark_resumes_to_the_complete_dataset(tmp_path):
    """Killed between the rename of ``rows/`` and the ``complete`` mark: the dataset is incomplete (not done, not
    loadable), and opening it again finishes it with the same rows."""
    reference = _synthetic_dataset(tmp_path / "reference").finalize()
    root = tmp_path / "crashed"
    with killed_at_the_complete_mark(), pytest.raises(KeyboardInterrupt):
        _synthetic_dataset(root).finalize()
    assert (root / "rows").is_dir() and (root / "shards").is_dir() and not is_complete(root)
    with pytest.raises(RuntimeError, match="incomplete"):
        TrajectoryDataset.load(root)
    writer = DatasetWriter(root, DatasetMeta(task="synthetic", num_points=8, gamma=0.5, seed=0, sources=[]))
    assert writer.done_chunks() == {0, 1}
    resumed = writer.finalize()
    assert is_complete(root) and (resumed.rows == reference.rows).all() and not (root / "shards").exists()


def _without_seeding(root):
    """Makes ``root``'s meta.json look written before the ``seeding`` field (per-worker seeds)."""
    meta = json.loads((root / "meta.json").read_text())
    del meta["seeding"]
    (root / "meta.json").write_text(json.dumps(meta))


def test_a_dataset_seeded_per_worker_loads_but_is_not_resumed(tmp_path):
    """Datasets collected before episodes were seeded one by one still load; an unfinished one is refused for
    resumption, which would mix the two seedings."""
    _synthetic_dataset(tmp_path / "complete").finalize()
    _without_seeding(tmp_path / "complete")
    assert TrajectoryDataset.load(tmp_path / "complete").meta.seeding == "worker"
    _synthetic_dataset(tmp_path / "unfinished")
    _without_seeding(tmp_path / "unfinished")
    with pytest.raises(ValueError, match="older version of the library, which seeded each worker"):
        DatasetWriter(
            tmp_path / "unfinished", DatasetMeta(task="synthetic", num_points=8, gamma=0.5, seed=0, sources=[])
        )


def test_writer_finalizes_in_chunk_order(tmp_path):
    meta = DatasetMeta(task="synthetic", num_points=8, gamma=0.5, seed=0, sources=[])
    writer = DatasetWriter(tmp_path, meta)
    written = {}
    for chunk in (1, 0):  # written out of order
        written[chunk] = trajectory_rows(
            synthetic_trajectory(3 + chunk, True),
            trajectory_id=0,
            source=0,
            noise_scale=0.0,
            expert_source=True,
            gamma=0.5,
        )
        writer.write_chunk(chunk, written[chunk])
    dataset = writer.finalize()
    assert dataset.lengths.tolist() == [4, 5]
    assert dataset.rows[keys.TRAJECTORY_ID].tolist() == [0] * 4 + [1] * 5
    # every other entry reads back from disk as written, dtype included
    expected = torch.cat([written[0], written[1]])
    for key in expected.exclude(keys.TRAJECTORY_ID).keys(include_nested=True, leaves_only=True):
        stored = dataset.rows[key]
        assert stored.dtype == expected[key].dtype and torch.equal(stored, expected[key]), key
    assert not (tmp_path / "shards").exists()


def test_two_worker_collection_equals_one_worker_and_keeps_the_thread_count(tmp_path, monkeypatch, one_thread):
    """Episodes are seeded one by one, not per worker: two workers collect the rows of one, reset seeds included,
    and no episode twice. The process's torch thread count is the caller's afterwards (TorchRL's collector raises
    it towards the count at import on shutdown; results computed after a collection must not depend on it)."""
    import torchrl

    monkeypatch.setattr(torchrl, "_THREAD_POOL_INIT", 4)
    sources = [Source("expert_noisy", 4, noise_scale=0.2)]
    kwargs = dict(seed=3, num_points=32, chunk_size=4, progress=False)
    dataset = collect(SHORT_REACH, tmp_path / "two", sources, num_workers=2, **kwargs)
    assert torch.get_num_threads() == 1
    assert dataset.num_trajectories == 4
    first_states = dataset.rows[keys.PRIVILEGED_STATE][dataset.starts]
    assert len(torch.unique(first_states, dim=0)) == 4
    one = collect(SHORT_REACH, tmp_path / "one", sources, num_workers=1, **kwargs)
    assert (one.rows == dataset.rows).all()
    assert (
        one.meta.shards[0]["reset_seeds"] == dataset.meta.shards[0]["reset_seeds"] == [3_000_000 + i for i in range(4)]
    )
