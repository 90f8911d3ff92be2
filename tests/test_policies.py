import dataclasses

import pytest
import torch
from conftest import SHORT_REACH
from tensordict import TensorDict
from torchrl.collectors import Collector

from torchrl_dalir import keys, make_env
from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.modules import MinMaxNormalizer, PointCloudEncoder, PolicyConfig, make_policy
from torchrl_dalir.modules.receding_horizon import receding_horizon
from torchrl_dalir.objectives import ConsistencyFlowMatchingLoss, DiffusionLoss, FlowMatchingLoss
from torchrl_dalir.training import train_policy

TINY = dict(down_dims=[16, 32, 64], point_hidden=[16, 32, 64], train_timesteps=20, ddim_steps=3, euler_steps=3)


def _policy(kind, seed=0):
    """``kind`` is ``dp``, ``fm`` or ``fm-sample`` (flow matching whose network predicts the clean chunk)."""
    torch.manual_seed(seed)
    kind, _, prediction = kind.partition("-")
    policy = make_policy(
        PolicyConfig(kind=kind, flow_prediction=prediction or "velocity", **TINY), action_dim=4, state_dim=4
    )
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 2 - 1)
    return policy


def _batch(n=8, points=16):
    torch.manual_seed(1)
    return TensorDict(
        {
            keys.POINT_CLOUD: torch.rand(n, 2, points, 3),
            keys.AGENT_POS: torch.rand(n, 2, 4),
            keys.ACTION_CHUNK: torch.rand(n, 16, 4) * 2 - 1,
        },
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


@pytest.mark.parametrize("p", [0.2, 0.9])  # 0.9: most channels need the full fallback
def test_top_k_masked_max_is_bit_identical_to_the_full_masked_max(p):
    from torchrl_dalir.modules.encoders import masked_max

    g = torch.Generator().manual_seed(0)
    features = torch.randn(2, 1, 2, 300, 64, generator=g).round(decimals=1)  # ties between points too
    keep = torch.rand(2, 32, 2, 300, generator=g) >= p
    keep[..., 0] |= ~keep.any(-1)
    expected = features.expand(2, 32, 2, 300, 64).masked_fill(~keep.unsqueeze(-1), float("-inf")).max(-2).values
    assert torch.equal(masked_max(features, keep), expected)
    assert torch.equal(masked_max(features, keep, top=1), expected)


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


def test_sample_rejects_noise_of_the_wrong_shape():
    policy = _policy("fm")
    cond = policy.encode(_batch()[keys.POINT_CLOUD], _batch()[keys.AGENT_POS])
    for bad in (
        torch.randn(8, 15, 4),
        torch.randn(4, 32, 4),
        torch.randn(8 * 16 * 4),
    ):  # the last two hold the right count
        with pytest.raises(ValueError, match="one chunk per condition"):
            policy.sample(cond, noise=bad)


@pytest.mark.parametrize("kind", ["dp", "fm", "fm-sample"])
def test_sampler_inverts_its_training_objective(kind):
    """With a perfect network the loss is zero and the sampler returns the demo chunk: loss and
    sampler agree on the direction of time (FM) and on what the network predicts (DP)."""
    policy = _policy(kind)
    batch = _batch()
    clean = torch.rand(8, 16, 4) * 1.8 - 0.9  # a normalised chunk inside DP's clipping range
    batch[keys.ACTION_CHUNK] = policy.action_normalizer.unnormalize(clean)
    target = policy.action_normalizer(batch[keys.ACTION_CHUNK])
    if kind == "fm":
        policy.network = lambda x, t, cond: (target - x) / (1 - t)[:, None, None]
        loss = FlowMatchingLoss(policy)(batch)["loss_flow_matching"]
    elif kind == "fm-sample":
        policy.network = lambda x, t, cond: target
        loss = FlowMatchingLoss(policy)(batch)["loss_flow_matching"]
    else:
        policy.unet.forward = lambda x, step, cond: target
        loss = DiffusionLoss(policy)(batch)["loss_diffusion"]
    assert loss.item() < 1e-8
    cond = policy.encode(batch[keys.POINT_CLOUD], batch[keys.AGENT_POS])
    for steps in (1, 3):
        policy.config.euler_steps = policy.config.ddim_steps = steps
        sampled = policy.sample(cond, noise=torch.randn(8, 16, 4))
        torch.testing.assert_close(sampled, batch[keys.ACTION_CHUNK], rtol=1e-4, atol=1e-4)


def test_diffusion_samples_stay_within_the_demo_action_range():
    policy = _policy("dp")  # untrained: its clean-chunk predictions are far from [-1, 1] before clipping
    cond = policy.encode(_batch()[keys.POINT_CLOUD], _batch()[keys.AGENT_POS])
    chunks = policy.sample(cond.repeat(8, 1), torch.Generator().manual_seed(0))
    low, high = policy.action_normalizer.low, policy.action_normalizer.high
    assert (chunks >= low - 1e-5).all() and (chunks <= high + 1e-5).all()


def test_policy_outputs_stay_within_the_env_action_bounds(trained_policy):
    """Chunks are clamped, in env units, to the bounds the env clips actions to: what the policy outputs (and a
    world model imagines) is what the simulator executes. ``load_policy`` sets the bounds of the policy's task."""
    from torchrl_dalir.envs import action_bounds

    low, high = action_bounds("reach")
    loaded = load_policy(trained_policy[1])
    assert torch.equal(loaded.action_low, low) and torch.equal(loaded.action_high, high)
    assert "action_low" not in loaded.state_dict()  # the env's bounds, not weights: checkpoints are unchanged
    policy = _policy("fm")
    policy.fit_normalizers(
        torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 10 - 5
    )  # demo actions beyond [-1, 1]
    cond = policy.encode(_batch()[keys.POINT_CLOUD], _batch()[keys.AGENT_POS])
    unbounded = policy.sample(cond, torch.Generator().manual_seed(0))
    assert ((unbounded < low) | (unbounded > high)).any()
    policy.set_action_bounds(low, high)
    chunks = policy.sample(cond, torch.Generator().manual_seed(0))
    assert ((chunks >= low) & (chunks <= high)).all() and torch.equal(chunks, unbounded.clamp(low, high))
    with pytest.raises(ValueError, match="low <= high"):
        policy.set_action_bounds(high, low)


def test_receding_horizon_executes_chunk_entries_1_to_8_and_replans_every_8_steps():
    from tensordict.nn import TensorDictModule
    from torchrl.envs import SerialEnv

    decisions = []

    def chunk(cloud):  # chunk entry i of decision d is 0.1 * d + 0.01 * i in every action dimension
        decisions.append(1)
        value = 0.1 * (len(decisions) - 1) + 0.01 * torch.arange(16.0)
        return value[:, None].expand(16, 4).expand(*cloud.shape[:-3], 16, 4)

    actor = receding_horizon(
        TensorDictModule(chunk, [keys.POINT_CLOUD], [keys.ACTION_CHUNK]), obs_steps=2, action_steps=8
    )
    env = SerialEnv(1, lambda: make_env(SHORT_REACH, seed=0, num_points=16, history=2))
    actions = env.rollout(24, actor, break_when_any_done=False)[keys.ACTION][0]
    env.close()
    step = torch.arange(24.0)
    expected = 0.1 * (step // 8) + 0.01 * (1 + step % 8)  # entries 1..8 (the current step on), 3 decisions
    torch.testing.assert_close(actions, expected[:, None].expand(24, 4))


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


@pytest.mark.parametrize(
    "kind, loss_class",
    [
        ("dp", DiffusionLoss),
        ("fm", FlowMatchingLoss),
        ("fm-sample", FlowMatchingLoss),
        ("fm", ConsistencyFlowMatchingLoss),
    ],
)
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


def test_checkpoint_reloads_the_ema_policy_identically(trained_policy, collected):
    cfg, path = trained_policy
    state = torch.load(path, weights_only=False)
    assert state["step"] == cfg.num_steps and state["task"] == "reach" and state["num_points"] == 64
    a, b = load_policy(path, task="reach"), load_policy(path)
    # the shipped weights are the EMA ones, not the last optimiser step's
    ema = {k.removeprefix("module."): v for k, v in state["ema"].items() if k.startswith("module.")}
    for name, value in a.state_dict().items():
        assert torch.equal(value, ema[name]), name
    assert any(not torch.equal(ema[k], v) for k, v in state["model"].items() if v.is_floating_point())
    # the action normalizer was fitted on the demos' actions and travels with the weights
    rows = collected.rows
    acting = rows[keys.ACTION][~rows[keys.IS_FINAL]]
    assert torch.equal(a.action_normalizer.low, acting.min(0).values) and torch.equal(
        a.action_normalizer.high, acting.max(0).values
    )
    batch = _batch(4, points=64)
    noise = torch.randn(4, 16, 4)
    cond_a = a.encode(batch[keys.POINT_CLOUD], batch[keys.AGENT_POS])
    cond_b = b.encode(batch[keys.POINT_CLOUD], batch[keys.AGENT_POS])
    assert torch.equal(a.sample(cond_a, noise=noise), b.sample(cond_b, noise=noise))
    with pytest.raises(ValueError, match="not 'door'"):
        load_policy(path, task="door")


def test_interrupted_training_resumes_to_the_same_weights(trained_policy, tmp_path, monkeypatch):
    from torchrl_dalir.training import loop

    cfg, _ = trained_policy
    straight = train_policy(dataclasses.replace(cfg, out=str(tmp_path / "straight")))
    save = loop.save_checkpoint

    def save_then_crash(path, payload):
        save(path, payload)
        raise KeyboardInterrupt  # killed right after the first checkpoint (step checkpoint_every)

    monkeypatch.setattr(loop, "save_checkpoint", save_then_crash)
    resumed_cfg = dataclasses.replace(cfg, out=str(tmp_path / "resumed"))
    with pytest.raises(KeyboardInterrupt):
        train_policy(resumed_cfg)
    path = resumed_cfg.run_dir() / "checkpoint.pt"
    assert torch.load(path, weights_only=False)["step"] == cfg.checkpoint_every < cfg.num_steps
    monkeypatch.setattr(loop, "save_checkpoint", save)
    resumed = torch.load(train_policy(resumed_cfg), weights_only=False)
    expected = torch.load(straight, weights_only=False)
    assert resumed["step"] == expected["step"] == cfg.num_steps
    for name, value in expected["policy_state"].items():
        assert torch.equal(resumed["policy_state"][name], value), name


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


def test_ema_decay_warms_up_caps_and_averages():
    from torchrl_dalir.training.loop import OptimConfig, ema_decay, make_ema

    assert ema_decay(0, 0.75, 0.9999) == 0.0
    assert ema_decay(15, 0.75, 0.9999) == 0.875  # 1 - 16 ** -0.75
    assert ema_decay(10**9, 0.75, 0.9999) == 0.9999
    model = torch.nn.Linear(1, 1, bias=False)
    torch.nn.init.constant_(model.weight, 1.0)
    ema = make_ema(model, OptimConfig())
    ema.update_parameters(model)  # the first update copies
    torch.nn.init.constant_(model.weight, 3.0)
    ema.update_parameters(model)
    decay = ema_decay(1, 0.75, 0.9999)
    torch.testing.assert_close(ema.module.weight, torch.full((1, 1), decay * 1.0 + (1 - decay) * 3.0))


def test_fit_stops_on_a_non_finite_loss(tmp_path):
    from torchrl.objectives import LossModule

    from torchrl_dalir.training.loop import OptimConfig, fit

    model = torch.nn.Linear(2, 1)

    class ExplodingLoss(LossModule):
        def forward(self, batch):
            return TensorDict({"loss": (model(batch["x"]) * float("nan")).mean()}, [])

    with pytest.raises(FloatingPointError, match="nan at step 0"):
        fit(
            ExplodingLoss(),
            model,
            lambda g: TensorDict({"x": torch.rand(4, 2, generator=g)}, [4]),
            5,
            OptimConfig(),
            tmp_path / "checkpoint.pt",
            lambda ema: {},
            progress=False,
        )
    assert not (tmp_path / "checkpoint.pt").exists()  # nothing half-trained is saved
