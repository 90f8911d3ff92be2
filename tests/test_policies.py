import dataclasses

import pytest
import torch
from conftest import SHORT_REACH
from tensordict import TensorDict
from torchrl.collectors import Collector

from torchrl_dalir import keys, make_env
from torchrl_dalir.modules import MinMaxNormalizer, PointCloudEncoder, PolicyConfig, make_policy
from torchrl_dalir.modules.receding_horizon import receding_horizon
from torchrl_dalir.objectives import ConsistencyFlowMatchingLoss, DiffusionLoss, FlowMatchingLoss
from torchrl_dalir.training import load_policy, train_policy

TINY = dict(down_dims=[16, 32, 64], point_hidden=[16, 32, 64], train_timesteps=20, ddim_steps=3, euler_steps=3)


def _policy(kind, seed=0):
    torch.manual_seed(seed)
    policy = make_policy(PolicyConfig(kind=kind, **TINY), action_dim=4, state_dim=4)
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 2 - 1)
    return policy


def _batch(n=8, points=16):
    torch.manual_seed(1)
    return TensorDict(
        {keys.POINT_CLOUD: torch.rand(n, 2, points, 3), keys.AGENT_POS: torch.rand(n, 2, 4), keys.ACTION_CHUNK: torch.rand(n, 16, 4) * 2 - 1},
        [n],
    )


def test_normalizer_round_trip_and_constant_dimensions():
    data = torch.stack([torch.linspace(-3, 5, 20), torch.full((20,), 0.7)], dim=-1)
    normalizer = MinMaxNormalizer(2).fit(data)
    normalized = normalizer(data)
    assert normalized[:, 0].min() == -1 and normalized[:, 0].max() == 1
    assert torch.allclose(normalized[:, 1], torch.zeros(20))  # a constant dimension is centred
    torch.testing.assert_close(normalizer.unnormalize(normalized), data)
    with pytest.raises(ValueError, match="NaN"):
        MinMaxNormalizer(2).fit(torch.tensor([[0.0, float("nan")]]))


def test_masked_pooling_equals_encoding_the_kept_points():
    encoder = PointCloudEncoder((16, 32, 64), out_dim=8)
    cloud = torch.randn(3, 50, 3)
    keep = torch.rand(3, 50) > 0.3
    shared = encoder.pool(encoder.point_features(cloud), keep)
    for i in range(3):
        torch.testing.assert_close(shared[i], encoder(cloud[i][keep[i]]))


@pytest.mark.parametrize("kind", ["dp", "fm"])
def test_policy_shapes_and_reproducible_sampling(kind):
    policy = _policy(kind)
    batch = _batch()
    cond = policy.encode(batch[keys.POINT_CLOUD], batch[keys.AGENT_POS])
    assert cond.shape == (8, policy.cond_dim)
    noise = torch.randn(8, 16, 4)
    a, b = policy.sample(cond, noise=noise), policy.sample(cond, noise=noise)
    assert a.shape == (8, 16, 4) and a.dtype == torch.float32 and torch.equal(a, b)
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    assert torch.equal(policy.sample(cond, g()), policy.sample(cond, g()))
    many = policy.sample(cond[:1].expand(32, -1), g())  # 32 candidates in one call
    assert many.shape == (32, 16, 4) and many.std(0).mean() > 0
    out = policy(batch.exclude(keys.ACTION_CHUNK))
    assert out[keys.ACTION_CHUNK].shape == (8, 16, 4)


def test_policy_rejects_bad_observations():
    policy = _policy("fm")
    with pytest.raises(ValueError, match="2-step history"):
        policy.encode(torch.rand(4, 32, 3), torch.rand(4, 2, 4))
    with pytest.raises(ValueError, match="agent_pos"):
        policy.encode(torch.rand(4, 2, 32, 3), torch.rand(4, 2, 7))
    cloud = torch.rand(4, 2, 32, 3)
    cloud[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        policy.encode(cloud, torch.rand(4, 2, 4))


@pytest.mark.parametrize("kind, loss_class", [("dp", DiffusionLoss), ("fm", FlowMatchingLoss), ("fm", ConsistencyFlowMatchingLoss)])
def test_training_lowers_the_loss(kind, loss_class):
    policy = _policy(kind)
    loss_module = loss_class(policy)
    batch = _batch(8)
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)

    def loss_value():
        torch.manual_seed(0)  # the same noise and steps for a fair comparison
        return sum(v for k, v in loss_module(batch).items() if k.startswith("loss"))

    before = loss_value().item()
    for _ in range(40):
        loss = loss_value()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert loss_value().item() < 0.5 * before


def test_checkpoint_reloads_identical(trained_policy):
    cfg, path = trained_policy
    state = torch.load(path, weights_only=False)
    assert state["step"] == cfg.num_steps and state["task"] == "reach" and state["num_points"] == 64
    a, b = load_policy(path, task="reach"), load_policy(path)
    batch = _batch(4, points=64)
    noise = torch.randn(4, 16, 4)
    cond_a = a.encode(batch[keys.POINT_CLOUD], batch[keys.AGENT_POS])
    cond_b = b.encode(batch[keys.POINT_CLOUD], batch[keys.AGENT_POS])
    assert torch.equal(a.sample(cond_a, noise=noise), b.sample(cond_b, noise=noise))
    with pytest.raises(ValueError, match="not 'door'"):
        load_policy(path, task="door")


def test_training_resumes_from_its_checkpoint(trained_policy):
    cfg, path = trained_policy
    longer = dataclasses.replace(cfg, num_steps=cfg.num_steps + 5)
    train_policy(longer)
    assert torch.load(path, weights_only=False)["step"] == cfg.num_steps + 5


def test_trained_policy_runs_8_of_16_in_rollout_and_collector(trained_policy):
    _, path = trained_policy
    policy = load_policy(path)
    calls = []
    policy.register_forward_hook(lambda *args: calls.append(1))
    actor = receding_horizon(policy, obs_steps=2, action_steps=8)
    from torchrl.envs import SerialEnv

    env = SerialEnv(1, lambda: make_env(SHORT_REACH, seed=0, num_points=64, history=2))
    rollout = env.rollout(24, actor, break_when_any_done=False)
    assert rollout[keys.ACTION].shape == (1, 24, 4) and len(calls) == 3
    collector = Collector(env, actor, frames_per_batch=16, total_frames=16)
    batch = next(iter(collector))
    collector.shutdown()
    assert batch[keys.ACTION].shape[-1] == 4 and batch.numel() == 16
