import json

import pytest
import torch
from conftest import SHORT_REACH, still_policy

from torchrl_dalir import keys
from torchrl_dalir.data import DatasetWriter, Source, TrajectoryDataset, collect
from torchrl_dalir.data.storage import DatasetMeta


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
    reloaded = collect(SHORT_REACH, collected.root, sources, seed=1, gamma=0.9, num_points=64, num_workers=1, chunk_size=2)
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


def test_interrupted_collection_resumes_to_the_same_data(tmp_path, monkeypatch):
    sources = [Source("expert", 2), Source("still", 1, policy=still_policy, expert=False)]
    kwargs = dict(seed=2, gamma=0.9, num_points=32, num_workers=1, chunk_size=1, progress=False)
    reference = collect(SHORT_REACH, tmp_path / "reference", sources, **kwargs)

    original = DatasetWriter.write_chunk
    def crash_after_two_chunks(self, chunk, rows, **info):
        if len(self.meta.shards) == 2:
            raise KeyboardInterrupt
        original(self, chunk, rows, **info)
    monkeypatch.setattr(DatasetWriter, "write_chunk", crash_after_two_chunks)
    with pytest.raises(KeyboardInterrupt):
        collect(SHORT_REACH, tmp_path / "resumed", sources, **kwargs)
    meta = json.loads((tmp_path / "resumed" / "meta.json").read_text())
    assert not meta["complete"] and len(meta["shards"]) == 2
    with pytest.raises(RuntimeError, match="incomplete"):
        TrajectoryDataset.load(tmp_path / "resumed")

    monkeypatch.setattr(DatasetWriter, "write_chunk", original)
    resumed = collect(SHORT_REACH, tmp_path / "resumed", sources, **kwargs)
    assert (resumed.rows == reference.rows).all()
    assert [s["chunk"] for s in resumed.meta.shards] == [0, 1, 2]


def test_writer_finalizes_in_chunk_order(tmp_path):
    from conftest import synthetic_trajectory

    from torchrl_dalir.data import trajectory_rows

    meta = DatasetMeta(task="synthetic", num_points=8, gamma=0.5, seed=0, sources=[])
    writer = DatasetWriter(tmp_path, meta)
    written = {}
    for chunk in (1, 0):  # written out of order
        written[chunk] = trajectory_rows(synthetic_trajectory(3 + chunk, True), trajectory_id=0, source=0, noise_scale=0.0, expert_source=True, gamma=0.5)
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


def test_two_worker_collection_seeds_workers_apart(tmp_path):
    """Each collector worker seeds its env and its noise differently: no duplicate episodes."""
    sources = [Source("expert_noisy", 4, noise_scale=0.2)]
    dataset = collect(SHORT_REACH, tmp_path, sources, seed=3, num_points=32, num_workers=2, chunk_size=4, progress=False)
    assert dataset.num_trajectories == 4
    first_states = dataset.rows[keys.PRIVILEGED_STATE][dataset.starts]
    assert len(torch.unique(first_states, dim=0)) == 4
