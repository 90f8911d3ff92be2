"""DP3's zarr stores imported as trajectory datasets, the trajectory split, the action-ablated world model and
the Table 4 command (issue 18)."""

import json
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchrl_dalir import keys
from torchrl_dalir.data import TrajectoryDataset, import_dp3_zarr, write_dp3_zarr
from torchrl_dalir.modules import LatentWorldModel

pytest.importorskip("zarr")

LENGTHS = (4, 6, 3)  # steps of the test store's episodes


def _episodes(channels: int = 6, points: int = 10, lengths=LENGTHS) -> list[dict]:
    """Episodes whose values tell where they come from: step s (counted over the store) has state [s, -s],
    action [s, 10 s] and points whose x is s and y the point's index."""
    episodes, step = [], 0
    for length in lengths:
        s = np.arange(step, step + length, dtype=np.float32)
        cloud = np.zeros((length, points, channels), np.float32)
        cloud[..., 0], cloud[..., 1] = s[:, None], np.arange(points)
        cloud[..., 3:] = 0.5  # colour
        episodes.append({"point_cloud": cloud, "state": np.stack([s, -s], -1), "action": np.stack([s, 10 * s], -1)})
        step += length
    return episodes


def test_import_keeps_every_step_of_every_episode_exactly(tmp_path):
    store = write_dp3_zarr(tmp_path / "drill.zarr", _episodes())
    dataset = import_dp3_zarr(store, tmp_path / "drill", num_points=None, gamma=0.5)
    rows = dataset.rows
    assert dataset.task == "drill" and dataset.meta.num_points == 10 and dataset.num_trajectories == 3
    assert dataset.lengths.tolist() == list(LENGTHS)  # an episode of L steps: L - 1 actions, L rows
    s = torch.arange(sum(LENGTHS), dtype=torch.float32)
    assert torch.equal(rows[keys.AGENT_POS], torch.stack([s, -s], -1))
    assert rows[keys.POINT_CLOUD].shape == (13, 10, 3)  # xyz only: the colour channels are dropped
    assert (
        torch.equal(rows[keys.POINT_CLOUD][..., 0], s[:, None].expand(13, 10))
        and rows[keys.POINT_CLOUD][..., 2].eq(0).all()
    )
    final = torch.tensor(
        [3, 9, 12]
    )  # the last step of each episode: its action (never followed by an observation) is dropped
    assert rows[keys.IS_FINAL].nonzero().squeeze(-1).tolist() == final.tolist()
    acting = ~rows[keys.IS_FINAL]
    assert (
        torch.equal(rows[keys.ACTION][acting], torch.stack([s, 10 * s], -1)[acting])
        and rows[keys.ACTION][final].eq(0).all()
    )
    assert rows[keys.TRAJECTORY_ID].tolist() == [0] * 4 + [1] * 6 + [2] * 3
    assert rows[keys.STEP].tolist() == [*range(4), *range(6), *range(3)]
    # no outcome in DP3's data: every demonstration is labeled a success, and meta.json says the label is assumed
    assert rows[keys.TERMINAL_LABEL].eq(1).all() and dataset.quality_counts() == {
        "expert": 3,
        "imperfect_success": 0,
        "failed": 0,
    }
    assert rows[keys.COMPLETION_TARGET][:4].tolist() == [0.125, 0.25, 0.5, 1.0]
    assert "assumed" in dataset.meta.sources[0]["terminal_label"] and keys.REWARD not in rows.keys()
    # complete, so loading it again gives the same rows
    assert TrajectoryDataset.load(tmp_path / "drill").meta.complete
    assert torch.equal(
        import_dp3_zarr(store, tmp_path / "drill", num_points=None, gamma=0.5).rows[keys.ACTION], rows[keys.ACTION]
    )


def test_import_samples_clouds_to_num_points(tmp_path):
    store = write_dp3_zarr(tmp_path / "pour.zarr", _episodes(channels=3, points=40))
    dataset = import_dp3_zarr(store, tmp_path / "pour", num_points=8, chunk_size=2)
    cloud = dataset.rows[keys.POINT_CLOUD]
    assert cloud.shape == (13, 8, 3) and dataset.meta.num_points == 8 and len(dataset.meta.shards) == 2
    assert all(len(frame[:, 1].unique()) == 8 for frame in cloud)  # 8 distinct points of the 40 in every frame


def _write(path, **changes):
    """A test store with arrays replaced (``None`` leaves one out) and episode ends given."""
    episodes = _episodes()
    arrays = {"data/" + k: np.concatenate([e[k] for e in episodes]) for k in ("point_cloud", "state", "action")}
    arrays["meta/episode_ends"] = np.cumsum(LENGTHS)
    arrays.update(changes)
    import zarr

    root = zarr.open_group(str(path), mode="w")
    for name, value in arrays.items():
        if value is not None:
            root[name] = value
    return path


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"data/action": None}, "no data/action"),
        ({"data/point_cloud": np.zeros((13, 10, 2), np.float32)}, "3 or 6"),
        ({"data/state": np.zeros((12, 2), np.float32)}, "data/state must be"),
        ({"meta/episode_ends": np.array([4, 5, 13])}, r"episodes \[1\] are too short"),
        ({"meta/episode_ends": np.array([4, 10])}, "end at 13"),
        ({"meta/episode_ends": np.array([4.0, 10.0, 13.0])}, "integer"),
    ],
)
def test_import_refuses_a_store_not_in_dp3_layout(tmp_path, changes, message):
    with pytest.raises(ValueError, match=message):
        import_dp3_zarr(_write(tmp_path / "bad.zarr", **changes), tmp_path / "out")
    assert not (tmp_path / "out").exists()  # refused before anything is written


def test_import_refuses_nan_naming_the_episode_and_a_missing_store(tmp_path):
    state = np.concatenate([e["state"] for e in _episodes()])
    state[5, 1] = np.nan  # step 5: episode 1
    with pytest.raises(ValueError, match="data/state holds 1 NaN .* episode 1"):
        import_dp3_zarr(_write(tmp_path / "nan.zarr", **{"data/state": state}), tmp_path / "out", num_points=None)
    with pytest.raises(FileNotFoundError, match="no DP3 zarr store"):
        import_dp3_zarr(tmp_path / "missing.zarr", tmp_path / "out2")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="not a zarr store|not in DP3's layout"):
        import_dp3_zarr(tmp_path / "empty", tmp_path / "out3")


def test_split_holds_out_whole_trajectories(tmp_path):
    from torchrl_dalir.training.latent_dynamics import latent_windows
    from torchrl_dalir.training.world_model import split_trajectories

    dataset = import_dp3_zarr(
        write_dp3_zarr(tmp_path / "s.zarr", _episodes(lengths=(5,) * 10)), tmp_path / "s", num_points=None
    )
    held = split_trajectories(dataset.num_trajectories, 0.3, seed=1)
    assert held.sum() == 3 and torch.equal(held, split_trajectories(10, 0.3, seed=1))  # seeded
    windows = latent_windows(dataset, torch.arange(len(dataset.rows), dtype=torch.float32)[:, None], action_steps=2)
    held_windows = held[windows[keys.TRAJECTORY_ID]]
    train_ids, test_ids = (
        set(windows[keys.TRAJECTORY_ID][~held_windows].tolist()),
        set(windows[keys.TRAJECTORY_ID][held_windows].tolist()),
    )
    assert not train_ids & test_ids and len(train_ids | test_ids) == 10
    # a window's future latent is a row of its own trajectory: k steps ahead, or its final row
    row_of = windows[keys.LATENT].long()
    future = windows[keys.FUTURE, keys.LATENT].long()
    assert torch.equal(dataset.rows[keys.TRAJECTORY_ID][future], dataset.rows[keys.TRAJECTORY_ID][row_of])
    assert ((future - row_of) <= 2).all() and ((future - row_of) >= 1).all()


def test_the_action_ablated_world_model_ignores_the_chunk():
    torch.manual_seed(0)
    latent, chunks = torch.randn(5, 16), torch.randn(2, 5, 8, 4)
    for action_input in (True, False):
        torch.manual_seed(0)
        model = LatentWorldModel(16, 4, hidden=32, layers=1, heads=2, action_input=action_input).eval()
        torch.nn.init.normal_(model.out[-1].weight, std=0.1)  # untrained, it would predict "no change" for any chunk
        first, second = model.imagine(latent, chunks[0]), model.imagine(latent, chunks[1])
        assert torch.equal(first, second) != action_input
    with pytest.raises(ValueError, match="8, 4"):  # it still checks the chunk's shape
        model(latent, torch.randn(5, 16, 4))


def test_table4_smoke_writes_the_table(tmp_path, monkeypatch):
    script = Path(__file__).resolve().parents[1] / "examples" / "paper" / "table4_real_world.py"
    args = ["preset=smoke", "made=true", f"out={tmp_path}"]
    monkeypatch.setattr(sys, "argv", ["x", *args])
    example = runpy.run_path(str(script), run_name="__main__")
    result = json.loads((tmp_path / "table4.json").read_text())
    assert (
        result["data"] == example["MADE_DATA"] == "made store (synthetic, DP3 layout)" and "synthetic" in result["note"]
    )
    assert result["command"] == " ".join(["python examples/paper/table4_real_world.py", *args])
    assert [row["task"] for row in result["table"]] == ["made-0"]
    row, run = result["table"][0], result["runs"][0]
    assert set(row) == {"task", "with_action", "without_action", "no_change"} and all(
        len(row[k]) == 1 for k in example["METHODS"]
    )
    assert run["with_action"] != run["without_action"] and run["held_out_trajectories"] == [4]
    assert (tmp_path / "table4.png").stat().st_size > 0 and "| WM w/ action |" in (tmp_path / "table4.md").read_text()
    monkeypatch.setattr(sys, "argv", ["x", "preset=smoke"])
    with pytest.raises(ValueError, match="stores=.* or made=true"):
        runpy.run_path(str(script), run_name="__main__")
