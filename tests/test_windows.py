import dataclasses

import torch
from conftest import SHORT_REACH, synthetic_trajectory

from torchrl_dalir import keys, make_env
from torchrl_dalir.data import DatasetWriter, trajectory_rows
from torchrl_dalir.data.collection import newest_frame
from torchrl_dalir.data.storage import DatasetMeta
from torchrl_dalir.data.windows import TrajectoryWindows
from torchrl_dalir.envs.history import latest_history


def _dataset(tmp_path, lengths=(20, 5)):
    writer = DatasetWriter(tmp_path, DatasetMeta(task="synthetic", num_points=8, gamma=0.5, seed=0, sources=[]))
    for i, n in enumerate(lengths):
        rows = trajectory_rows(
            synthetic_trajectory(n, i % 2 == 0),
            trajectory_id=i,
            source=0,
            noise_scale=0.0,
            expert_source=True,
            gamma=0.5,
        )
        writer.write_chunk(i, rows)
    return writer.finalize()


def test_every_action_step_anchors_a_window(tmp_path):
    dataset = _dataset(tmp_path)
    windows = TrajectoryWindows(dataset)
    assert len(windows) == 20 + 5
    batch = windows[torch.arange(len(windows))]
    assert batch[keys.STEP].tolist() == list(range(20)) + list(range(5))


def test_padding_and_masks(tmp_path):
    windows = TrajectoryWindows(_dataset(tmp_path), obs_steps=2, horizon=16, future_offset=8)
    first = windows[[0]]  # t = 0: the observation before the start and the first action are padding
    assert first[keys.OBS_MASK].tolist() == [[True, False]]
    assert first[keys.AGENT_POS][0].squeeze(-1).tolist() == [0.0, 0.0]
    actions = first[keys.ACTION_CHUNK][0, :, 0]
    assert actions.tolist() == [0.0] + list(range(15))  # chunk covers t-1 .. t+14; t-1 repeats a_0
    assert first[keys.ACTION_MASK][0].tolist() == [True] + [False] * 15
    assert first["future", keys.AGENT_POS].item() == 8.0 and not first[keys.FUTURE_MASK].item()

    last = windows[[19]]  # t = 19 = T - 1, the last action of a 20-step episode
    assert last[keys.AGENT_POS][0].squeeze(-1).tolist() == [18.0, 19.0]
    assert last[keys.ACTION_CHUNK][0, :, 0].tolist() == [18.0, 19.0] + [19.0] * 14  # repeats a_{T-1}
    assert last[keys.ACTION_MASK][0].tolist() == [False, False] + [True] * 14
    # the future is the final observation s_T (agent_pos 20) and it is marked as padded
    assert last["future", keys.AGENT_POS].item() == 20.0 and last[keys.FUTURE_MASK].item()
    assert last["future", keys.COMPLETION_TARGET].item() == 1.0

    exact = windows[[12]]  # t + 8 = T: the real final observation, not padding
    assert exact["future", keys.AGENT_POS].item() == 20.0 and not exact[keys.FUTURE_MASK].item()


def test_windows_never_cross_episodes(tmp_path):
    windows = TrajectoryWindows(_dataset(tmp_path), obs_steps=2, horizon=16, future_offset=8)
    second = windows[[20, 24]]  # the 5-step episode
    assert second[keys.AGENT_POS][0].squeeze(-1).tolist() == [0.0, 0.0]
    assert second[keys.ACTION_CHUNK][1, :, 0].max().item() == 4.0
    assert second["future", keys.AGENT_POS].squeeze(-1).tolist() == [5.0, 5.0]
    assert (second[keys.TERMINAL_LABEL] == 0).all()


def test_sampling_is_seeded(tmp_path):
    windows = TrajectoryWindows(_dataset(tmp_path))
    a = windows.sample(6, generator=torch.Generator().manual_seed(0))
    b = windows.sample(6, generator=torch.Generator().manual_seed(0))
    assert (a == b).all() and a[keys.POINT_CLOUD].shape == (6, 2, 8, 3)


def test_env_history_equals_the_windows_and_the_diagnostics_history(tmp_path):
    """One rule: the env's stacked history (CatFrames), the training windows' and
    ``latest_history``'s (the reranking diagnostics') are the same for the same episode."""
    env = make_env(dataclasses.replace(SHORT_REACH, max_steps=6), seed=0, num_points=16, history=3)
    rollout = env.rollout(10)  # random actions, truncated after 6 steps
    env.close()
    assert rollout.shape == (6,) and rollout["next", keys.DONE][-1].item()
    writer = DatasetWriter(tmp_path, DatasetMeta(task="reach", num_points=16, gamma=0.9, seed=0, sources=[]))
    frames = newest_frame(rollout)  # what a collection stores
    writer.write_chunk(
        0, trajectory_rows(frames, trajectory_id=0, source=0, noise_scale=0.0, expert_source=False, gamma=0.9)
    )
    windows = TrajectoryWindows(writer.finalize(), obs_steps=3, horizon=3, future_offset=1)
    batch = windows[torch.arange(len(windows))]
    for key in (keys.POINT_CLOUD, keys.AGENT_POS):
        assert torch.equal(batch[key], rollout[key])
        diagnostics = [torch.stack(latest_history(list(frames[key][: t + 1]), 3)) for t in range(len(rollout))]
        assert torch.equal(torch.stack(diagnostics), rollout[key])
    assert batch[keys.OBS_MASK][:3].tolist() == [[True, True, False], [True, False, False], [False, False, False]]
