import pytest
import torch
from conftest import synthetic_trajectory
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Categorical, Composite, LazyTensorStorage, ReplayBuffer, Unbounded
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_dalir import keys
from torchrl_dalir.data import (
    TerminalLabelTransform,
    completion_targets,
    dense_reward_targets,
    quality_tag,
    trajectory_rows,
)

EXPERT, IMPERFECT, FAILED = range(3)  # indices into keys.QUALITY_TAGS


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
        {
            keys.REWARD: torch.tensor([1.0, 2.0, 0.0, 4.0, 0.0, 0.0]),
            keys.IS_FINAL: torch.tensor([0, 0, 1, 0, 0, 1]).bool(),
        },
        [6],
    )
    targets = dense_reward_targets(rows, gamma=0.5)
    # reward-to-go: 1 + 0.5*2 = 2, 2, 0 | 4, 0, 0; divided by the largest (4)
    assert torch.equal(targets, torch.tensor([0.5, 0.5, 0.0, 1.0, 0.0, 0.0]))
    # negative shaped rewards (Adroit Pen's): reward-to-go -1 + 0.5*2 = 0, 2, 0 | -4, 0, 0
    # mapped from [-4, 2] onto [0, 1]
    rows[keys.REWARD] = torch.tensor([-1.0, 2.0, 0.0, -4.0, 0.0, 0.0])
    assert torch.allclose(dense_reward_targets(rows, gamma=0.5), torch.tensor([4, 6, 4, 0, 4, 4]) / 6)


def rollout(done, success, **extra) -> TensorDict:
    """A rollout in TorchRL's layout ``[..., T]`` with the given ``("next", "done")`` and
    ``("next", "success")`` flags."""
    done, success = torch.tensor(done, dtype=torch.bool), torch.tensor(success, dtype=torch.bool)
    return TensorDict(
        {"next": {keys.DONE: done[..., None], keys.SUCCESS: success[..., None]}, **extra}, batch_size=done.shape
    )


def formula(done, success, gamma):
    """The targets and labels of a flat rollout, one trajectory at a time: step t of a T-action
    trajectory gets gamma^(T - t) * y_T, y_T = 1 if success was set at any of its steps."""
    done, success = done.flatten().tolist(), success.flatten().tolist()
    targets, labels, start = [], [], 0
    for end in [i + 1 for i, d in enumerate(done) if d]:
        y, num_actions = float(any(success[start:end])), end - start
        targets += [gamma ** (num_actions - t) * y for t in range(num_actions)]
        labels += [y] * num_actions
        start = end
    assert start == len(done), "the rollout ends with an incomplete trajectory"
    return torch.tensor(targets, dtype=torch.float64).float(), torch.tensor(labels)


def assert_follows_formula(data, gamma):
    targets, labels = formula(data["next", keys.DONE], data["next", keys.SUCCESS], gamma)
    assert torch.equal(data[keys.COMPLETION_TARGET].flatten(), targets)
    assert torch.equal(data[keys.TERMINAL_LABEL].flatten(), labels)
    assert data[keys.COMPLETION_TARGET].shape == data.shape and data[keys.QUALITY].dtype == torch.int64
    return labels


def test_label_transform_exact_values():
    # a success after 3 actions, a time-out after 2, and a 4-action trajectory whose success flag is set mid-way
    data = rollout([0, 0, 1, 0, 1, 0, 0, 0, 1], [0, 0, 1, 0, 0, 0, 1, 0, 0])
    labeled = TerminalLabelTransform(gamma=0.5).inv(data)
    assert keys.COMPLETION_TARGET not in data.keys()  # inv labels a shallow copy
    torch.testing.assert_close(
        labeled[keys.COMPLETION_TARGET],
        torch.tensor([0.125, 0.25, 0.5, 0, 0, 0.0625, 0.125, 0.25, 0.5]),
        rtol=0,
        atol=0,
    )
    assert torch.equal(labeled[keys.TERMINAL_LABEL], torch.tensor([1.0, 1, 1, 0, 0, 1, 1, 1, 1]))
    assert torch.equal(labeled[keys.QUALITY], torch.tensor([IMPERFECT] * 3 + [FAILED] * 2 + [IMPERFECT] * 4))
    assert_follows_formula(labeled, 0.5)

    undiscounted = TerminalLabelTransform(gamma=1.0, expert_source=True).inv(data)
    assert torch.equal(undiscounted[keys.COMPLETION_TARGET], undiscounted[keys.TERMINAL_LABEL])
    assert torch.equal(undiscounted[keys.QUALITY], torch.tensor([EXPERT] * 3 + [FAILED] * 2 + [EXPERT] * 4))
    with pytest.raises(ValueError, match="gamma"):
        TerminalLabelTransform(gamma=1.5)


def test_label_transform_with_a_leading_batch_dim():
    done = [[0, 1, 0, 0, 1, 1], [0, 0, 0, 0, 0, 1]]
    success = [[0, 1, 0, 0, 0, 1], [0, 0, 0, 0, 0, 0]]
    data = rollout(done, success)
    labels = TerminalLabelTransform(gamma=0.9, expert_source=True)
    labeled = labels.inv(data)
    assert labeled[keys.COMPLETION_TARGET].shape == (2, 6)
    assert_follows_formula(labeled, 0.9)
    for row in range(2):  # each row is labeled on its own: trajectories never run across rows
        assert (labels.inv(data[row]) == labeled[row]).all()
    assert torch.equal(labeled[keys.QUALITY][0], torch.tensor([EXPERT] * 2 + [FAILED] * 3 + [EXPERT]))


def test_label_transform_refuses_incomplete_trajectories_and_envs():
    labels = TerminalLabelTransform(gamma=0.9)
    with pytest.raises(ValueError, match="incomplete"):
        labels.inv(rollout([[0, 1, 1], [0, 1, 0]], [[0, 0, 0], [0, 0, 0]]))
    with pytest.raises(ValueError, match="time"):
        labels.inv(rollout([], []))
    with pytest.raises(KeyError, match="inv"):  # forward only passes labeled samples through
        labels(rollout([1], [1]))
    with pytest.raises(ValueError, match="not in an env"):
        TransformedEnv(TwoOutcomeEnv(), TerminalLabelTransform(gamma=0.9))


def test_label_transform_reads_the_padding_mask():
    # TorchRL's zero-padded trajectory batches: 3 actions, then 2 actions and a padded step
    mask = torch.tensor([[1, 1, 1], [1, 1, 0]], dtype=torch.bool)
    data = rollout([[0, 0, 1], [0, 1, 0]], [[0, 0, 1], [0, 1, 0]], collector={"mask": mask})
    labeled = TerminalLabelTransform(gamma=0.5).inv(data)
    assert torch.equal(labeled[keys.COMPLETION_TARGET], torch.tensor([[0.125, 0.25, 0.5], [0.25, 0.5, 0.0]]))
    assert torch.equal(labeled[keys.QUALITY], torch.tensor([[IMPERFECT] * 3, [IMPERFECT, IMPERFECT, 0]]))
    data["next", keys.DONE][1, 1] = False  # the second trajectory did not end before the padding
    with pytest.raises(ValueError, match="incomplete"):
        TerminalLabelTransform(gamma=0.5).inv(data)


def test_trajectory_rows_use_the_transform():
    trajectory = synthetic_trajectory(4, True)
    labeled = TerminalLabelTransform(gamma=0.9).inv(trajectory)
    rows = trajectory_rows(trajectory, trajectory_id=0, source=0, noise_scale=0.0, expert_source=False, gamma=0.9)
    assert torch.equal(rows[keys.COMPLETION_TARGET][:4], labeled[keys.COMPLETION_TARGET])
    assert torch.equal(rows[keys.COMPLETION_TARGET], completion_targets(4, 1.0, 0.9))


class TwoOutcomeEnv(EnvBase):
    """A task stand-in with a success flag, whatever the actions: even episodes succeed after 3
    actions (and terminate), odd ones time out after 4."""

    def __init__(self):
        super().__init__()
        flag = Categorical(2, shape=(1,), dtype=torch.bool)
        self.observation_spec = Composite({keys.STEP: Unbounded((1,)), keys.SUCCESS: flag.clone()})
        self.action_spec = Unbounded((1,))
        self.reward_spec = Unbounded((1,))
        self.full_done_spec = Composite({key: flag.clone() for key in (keys.DONE, keys.TERMINATED, keys.TRUNCATED)})
        self.episode, self.t = -1, 0

    def _reset(self, tensordict=None):
        self.episode, self.t = self.episode + 1, 0
        return self.full_done_spec.zero().update(
            {keys.STEP: torch.zeros(1), keys.SUCCESS: torch.zeros(1, dtype=torch.bool)}
        )

    def _step(self, tensordict):
        self.t += 1
        success = torch.tensor([self.episode % 2 == 0 and self.t == 3])
        truncated = torch.tensor([self.t == 4])
        return TensorDict(
            {
                keys.STEP: torch.full((1,), float(self.t)),
                keys.SUCCESS: success,
                keys.REWARD: torch.zeros(1),
                keys.DONE: success | truncated,
                keys.TERMINATED: success,
                keys.TRUNCATED: truncated,
            }
        )

    def _set_seed(self, seed):
        return seed


def test_label_transform_as_collector_postproc():
    # 14 frames hold a success (3 actions) and a time-out (4 actions) twice: every batch ends at an episode end
    labels = TerminalLabelTransform(gamma=0.9, expert_source=True)
    collector = Collector(TwoOutcomeEnv(), None, frames_per_batch=14, total_frames=28, postproc=labels.inv)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        y = assert_follows_formula(batch, 0.9)
        assert y.sum() == 6 and (1 - y).sum() == 8
        assert torch.equal(batch[keys.QUALITY], torch.where(y.bool(), EXPERT, FAILED))


def test_label_transform_on_collector_trajectories():
    # the collector assembles whole trajectories out of 5-frame batches and writes them to the buffer
    buffer = ReplayBuffer(storage=LazyTensorStorage(100), transform=TerminalLabelTransform(gamma=0.9), batch_size=4)
    collector = Collector(
        TwoOutcomeEnv(), None, frames_per_batch=5, total_frames=30, trajs_per_batch=1, replay_buffer=buffer
    )
    for _ in collector:
        pass
    collector.shutdown()
    stored = buffer[:]
    assert len(buffer) >= 21 and stored["next", keys.DONE][-1]
    y = assert_follows_formula(stored, 0.9)
    assert y.any() and not y.all()

    # padded batches of complete trajectories, as the collector yields them without a buffer
    collector = Collector(
        TwoOutcomeEnv(), None, frames_per_batch=5, total_frames=15, trajs_per_batch=2, traj_format="padded"
    )
    batch = next(iter(collector))
    collector.shutdown()
    labeled = TerminalLabelTransform(gamma=0.9).inv(batch)
    mask = batch["collector", "mask"]
    for row in range(2):
        assert_follows_formula(labeled[row][mask[row]], 0.9)


def test_label_transform_in_a_replay_buffer():
    data = rollout(
        [[0, 0, 1, 0, 1], [1, 0, 0, 0, 1]],
        [[0, 0, 1, 0, 0], [0, 0, 0, 0, 0]],
        observation=torch.arange(10.0).view(2, 5),
    )
    buffer = ReplayBuffer(storage=LazyTensorStorage(10), transform=TerminalLabelTransform(gamma=0.5), batch_size=3)
    buffer.extend(data)  # labeled on extend; each row of the batch is stored as one [5] item
    assert torch.equal(buffer[:][keys.COMPLETION_TARGET], torch.tensor([[0.125, 0.25, 0.5, 0, 0], [0, 0, 0, 0, 0]]))
    sample = buffer.sample()
    assert sample.shape == (3, 5)
    for item in sample:  # samples keep the labels written on extend
        row = int(item["observation"][0]) // 5
        assert torch.equal(item[keys.COMPLETION_TARGET], buffer[:][keys.COMPLETION_TARGET][row])
