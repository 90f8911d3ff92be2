import pytest
import torch
from conftest import synthetic_trajectory
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.data import completion_targets, dense_reward_targets, quality_tag, trajectory_rows


def test_completion_targets_formula():
    targets = completion_targets(3, 1.0, 0.5)
    assert torch.equal(targets, torch.tensor([0.125, 0.25, 0.5, 1.0]))
    assert torch.equal(completion_targets(4, 0.0, 0.9), torch.zeros(5))
    with pytest.raises(ValueError):
        completion_targets(3, 1.0, 0.0)


def test_quality_tags():
    assert keys.QUALITY_TAGS[quality_tag(True, expert_source=True)] == "expert"
    assert keys.QUALITY_TAGS[quality_tag(True, expert_source=False)] == "imperfect_success"
    assert keys.QUALITY_TAGS[quality_tag(False, expert_source=True)] == "failed"


@pytest.mark.parametrize("success", [True, False])
def test_trajectory_rows(success):
    trajectory = synthetic_trajectory(5, success)
    rows = trajectory_rows(trajectory, trajectory_id=7, source=2, noise_scale=0.1, expert_source=False, gamma=0.9)
    assert rows.shape == (6,)
    # rows 0..4 are the observations before each action; row 5 is the final observation s_T
    assert torch.equal(rows[keys.AGENT_POS].squeeze(-1), torch.arange(6.0))
    assert torch.equal(rows[keys.POINT_CLOUD][5], trajectory["next", keys.POINT_CLOUD][4])
    assert torch.equal(rows[keys.IS_FINAL], torch.tensor([False] * 5 + [True]))
    assert torch.equal(rows[keys.ACTION][:5], trajectory[keys.ACTION]) and not rows[keys.ACTION][5].any()
    expected = torch.tensor([0.9**5, 0.9**4, 0.9**3, 0.9**2, 0.9, 1.0]) * float(success)
    torch.testing.assert_close(rows[keys.COMPLETION_TARGET], expected)
    assert rows[keys.SUCCESS][5].item() is success and not rows[keys.SUCCESS][:5].any()
    assert (rows[keys.TERMINAL_LABEL] == float(success)).all()
    assert (rows[keys.TRAJECTORY_ID] == 7).all() and (rows[keys.SOURCE] == 2).all()
    tag = "imperfect_success" if success else "failed"
    assert (rows[keys.QUALITY] == keys.QUALITY_TAGS.index(tag)).all()


def test_incomplete_trajectory_is_refused():
    trajectory = synthetic_trajectory(4, True)
    trajectory["next", keys.DONE][-1] = False
    with pytest.raises(ValueError, match="complete"):
        trajectory_rows(trajectory, trajectory_id=0, source=0, noise_scale=0.0, expert_source=True, gamma=0.9)


def test_dense_reward_targets_are_normalised_reward_to_go_per_trajectory():
    # two trajectories of 2 actions each (3 rows: s_0, s_1, s_T); the final row has no reward
    rows = TensorDict(
        {keys.REWARD: torch.tensor([1.0, 2.0, 0.0, 4.0, 0.0, 0.0]), keys.IS_FINAL: torch.tensor([0, 0, 1, 0, 0, 1]).bool()}, [6]
    )
    targets = dense_reward_targets(rows, gamma=0.5)
    # reward-to-go: 1 + 0.5*2 = 2, 2, 0 | 4, 0, 0; divided by the largest (4)
    assert torch.equal(targets, torch.tensor([0.5, 0.5, 0.0, 1.0, 0.0, 0.0]))
