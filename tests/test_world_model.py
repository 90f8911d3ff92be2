import dataclasses
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_dalir import RerankingActor, keys
from torchrl_dalir.checkpoints import load_policy, load_world_model
from torchrl_dalir.modules import LatentEncoder, LatentWorldModel, PolicyConfig, TaskCompletionScorer, make_policy
from torchrl_dalir.objectives import LatentDynamicsLoss, TaskCompletionLoss
from torchrl_dalir.training import train_world_model
from torchrl_dalir.utils import weights_digest


def _train(loss_module, params, steps=80, lr=3e-3):
    optimizer = torch.optim.Adam(params, lr=lr)
    values = []
    for _ in range(steps):
        loss = sum(v for k, v in loss_module().items() if k.startswith("loss"))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        values.append(loss.item())
    return values


def test_untrained_world_model_predicts_no_change():
    wm = LatentWorldModel(16, 4, hidden=32, layers=1, heads=2)
    latent = torch.randn(5, 16)
    assert torch.equal(wm.imagine(latent, torch.randn(5, 8, 4)), latent)
    with pytest.raises(ValueError, match="8, 4"):
        wm(latent, torch.randn(5, 16, 4))


def test_dynamics_loss_falls_below_no_change():
    torch.manual_seed(0)
    wm = LatentWorldModel(16, 4, hidden=32, layers=1, heads=2)
    latent, actions = torch.randn(64, 16), torch.rand(64, 8, 4) * 2 - 1
    wm.action_normalizer.fit(actions)
    future = latent + actions.mean(1).repeat(1, 4)  # a residual that depends on the actions
    batch = TensorDict({"latent": latent, "future": {"latent": future}, keys.ACTION_CHUNK: actions}, [64])
    loss = LatentDynamicsLoss(wm)
    values = _train(lambda: loss(batch), wm.parameters(), steps=150)
    no_change = ((latent - future) ** 2).mean().item()
    assert values[0] == pytest.approx(no_change, rel=1e-4) and values[-1] < 0.2 * no_change


def test_task_completion_loss_falls():
    torch.manual_seed(0)
    policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]), 4, 4)
    encoder = LatentEncoder.from_policy(policy)
    scorer = TaskCompletionScorer(encoder.latent_dim, hidden=32)
    cloud = torch.rand(32, 40, 3)
    target = (cloud[:, :, 0].mean(-1) > 0.5).float()  # completion depends on where the points are
    rows = TensorDict(
        {keys.POINT_CLOUD: cloud, keys.AGENT_POS: torch.rand(32, 4), keys.COMPLETION_TARGET: target}, [32]
    )
    loss = TaskCompletionLoss(encoder, scorer)
    values = _train(lambda: loss(rows), [*encoder.parameters(), *scorer.parameters()])
    assert values[-1] < 0.5 * values[0]
    # the policy's own encoder was copied, not shared
    assert not any(p is q for p in encoder.parameters() for q in policy.parameters())


def test_scorer_metrics_exact_values():
    from torchrl_dalir.training.world_model import _scorer_metrics

    metrics = _scorer_metrics(torch.tensor([0.05, 0.95]), torch.tensor([0.0, 1.0]))
    assert metrics["brier"] == pytest.approx(0.0025)  # both off by 0.05
    assert metrics["calibration_error"] == pytest.approx(0.05)  # two bins of weight 1/2, each off by 0.05
    overconfident = _scorer_metrics(torch.tensor([0.9, 0.9, 0.9, 0.9]), torch.tensor([1.0, 0.0, 1.0, 0.0]))
    assert overconfident["calibration_error"] == pytest.approx(0.4)  # one bin: says 0.9, is 0.5


def test_world_model_checkpoint_and_metrics(trained_world_model, collected, monkeypatch):
    from torchrl_dalir.training import world_model as stage
    from torchrl_dalir.training.world_model import encode_rows, split_trajectories

    cfg, path, _ = trained_world_model
    parts = load_world_model(path)
    assert parts.task == "reach"
    held = split_trajectories(5, cfg.held_out_fraction, cfg.seed)
    assert (
        torch.load(path, weights_only=False)["held_out_trajectories"]
        == held.nonzero().flatten().tolist()
        == parts.held_out_trajectories
    )
    assert held.sum() == 2  # 40 % of 5 trajectories
    # the reported Brier score is the loaded scorer's, on the held-out trajectories' rows only
    rows = collected.rows
    held_rows = held[rows[keys.TRAJECTORY_ID]]
    probabilities = torch.sigmoid(parts.scorer(encode_rows(parts.encoder, rows[held_rows])))
    # written in place batch by batch, a ragged last batch included: the rows' latents in one pass
    latents = encode_rows(parts.encoder, rows, batch_size=7)
    assert len(rows) % 7 and latents.dtype == torch.float32
    torch.testing.assert_close(
        latents, parts.encoder(rows[keys.POINT_CLOUD], rows[keys.AGENT_POS]), rtol=1e-5, atol=1e-6
    )
    brier = ((probabilities - rows[keys.COMPLETION_TARGET][held_rows]) ** 2).mean().item()
    assert (
        parts.metrics["brier"] == pytest.approx(brier, abs=1e-6) and parts.metrics["held_out_rows"] == held_rows.sum()
    )
    assert parts.metrics["wm_mse"] != parts.metrics["no_change_mse"]
    # the scorer ensemble's held-out metrics are the loaded ensemble's, on imagined latents of
    # the held-out windows' recorded chunks
    from torchrl_dalir.data import TrajectoryDataset
    from torchrl_dalir.data.windows import TrajectoryWindows
    from torchrl_dalir.objectives.latent_dynamics import LATENT
    from torchrl_dalir.training.world_model import held_out_imagined_metrics

    kept = (
        keys.ACTION,
        keys.IS_FINAL,
        keys.TRAJECTORY_ID,
        keys.STEP,
        keys.COMPLETION_TARGET,
        keys.TERMINAL_LABEL,
        keys.QUALITY,
    )
    latent_rows = TensorDict({LATENT: encode_rows(parts.encoder, rows), **{k: rows[k] for k in kept}}, [len(rows)])
    windows = TrajectoryWindows(
        TrajectoryDataset(collected.root, collected.meta, latent_rows),
        obs_steps=1,
        horizon=8,
        future_offset=8,
        observation_keys=(LATENT,),
    )
    batch = windows[held[latent_rows[keys.TRAJECTORY_ID][windows.anchors]].nonzero().squeeze(-1)]
    batch[LATENT] = batch[LATENT][:, -1]
    imagined = held_out_imagined_metrics(parts.scorer, parts.ensemble, parts.world_model, batch)
    for name, value in imagined.items():
        assert parts.metrics[name] == pytest.approx(value, abs=1e-6), name
    assert imagined["ensemble_std"] > 0
    monkeypatch.setattr(stage, "load_policy", lambda *a, **k: pytest.fail("a finished run was redone"))
    assert train_world_model(cfg) == path


def test_reranking_actor_from_checkpoints(trained_world_model, tmp_path):
    _, wm_path, policy_path = trained_world_model
    actor = RerankingActor.from_checkpoints(policy_path, wm_path, num_candidates=3)
    assert load_world_model(wm_path).policy_digest == weights_digest(
        load_policy(policy_path)
    )  # checked on every pairing
    obs = TensorDict({keys.POINT_CLOUD: torch.rand(2, 2, 64, 3), keys.AGENT_POS: torch.rand(2, 2, 4)}, [2])
    assert actor(obs)[keys.ACTION_CHUNK].shape == (2, 16, 4)
    state = torch.load(wm_path, weights_only=False)
    state["task"] = "disassemble"
    other = tmp_path / "other_task.pt"  # not next to the fixture's checkpoints, which other tests list
    torch.save(state, other)
    with pytest.raises(ValueError, match="for task 'disassemble'"):
        RerankingActor.from_checkpoints(policy_path, other)


def test_dense_reward_oracle_scorer(trained_world_model):
    cfg, sparse_path, _ = trained_world_model
    oracle = dataclasses.replace(cfg, scorer_target="dense_reward")
    path = train_world_model(oracle)
    assert path != sparse_path and path.parent.name.endswith("_dense_reward")
    state = torch.load(path, weights_only=False)
    assert state["config"]["scorer_target"] == "dense_reward"
    # same data, same seed: only the scorer's targets differ
    assert not torch.equal(
        state["scorer_state"]["net.0.weight"],
        torch.load(sparse_path, weights_only=False)["scorer_state"]["net.0.weight"],
    )
    with pytest.raises(ValueError, match="scorer_target"):
        dataclasses.replace(cfg, scorer_target="reward")
    with pytest.raises(ValueError, match="no oracle on door: its dense reward grows with the palm-to-handle distance"):
        dataclasses.replace(cfg, scorer_target="dense_reward", task="door")


def test_frozen_encoder_keeps_the_policys_encoder_and_trains_the_scorer_on_its_latents(trained_world_model):
    from torchrl_dalir.modules import LatentEncoder

    cfg, finetuned_path, policy_path = trained_world_model
    frozen = dataclasses.replace(cfg, encoder="frozen", frozen_scorer_steps=40)
    path = train_world_model(frozen)
    assert path != finetuned_path and path.parent.name == "seed0_frozen"
    parts = load_world_model(path)
    policy_encoder = LatentEncoder.from_policy(load_policy(policy_path))
    for name, value in policy_encoder.state_dict().items():
        assert torch.equal(parts.encoder.state_dict()[name], value), name
    assert not torch.equal(
        parts.encoder.state_dict()["point_encoder.point_mlp.0.weight"],
        load_world_model(finetuned_path).encoder.state_dict()["point_encoder.point_mlp.0.weight"],
    )
    assert torch.load(path, weights_only=False)["encoder_mode"] == "frozen"
    with pytest.raises(ValueError, match="encoder"):
        dataclasses.replace(cfg, encoder="thawed")


def test_extra_data_joins_the_mixed_data(trained_world_model, collected):
    from torchrl_dalir.training.world_model import training_data

    cfg, _, _ = trained_world_model
    (Path(cfg.data) / "reach" / "more").symlink_to(collected.root)
    joined = training_data(dataclasses.replace(cfg, extra_data=["more"]))
    assert joined.num_trajectories == 2 * collected.num_trajectories
    assert len(joined.meta.sources) == 2 * len(collected.meta.sources)
    for i in range(collected.num_trajectories):
        second = joined.trajectory(collected.num_trajectories + i)
        assert torch.equal(second[keys.POINT_CLOUD], collected.trajectory(i)[keys.POINT_CLOUD])
        assert (second[keys.TRAJECTORY_ID] == collected.num_trajectories + i).all()
        assert (second[keys.SOURCE] == collected.trajectory(i)[keys.SOURCE] + len(collected.meta.sources)).all()
    assert dataclasses.replace(cfg, extra_data=["more"]).run_dir().name == "seed0+more"


def test_the_scorer_ensemble_can_learn_from_chosen_sources_only(trained_world_model, collected):
    cfg, path, _ = trained_world_model
    assert load_world_model(path).metrics["ensemble_windows"] == sum(  # every training window by default
        len(collected.trajectory(i)) - 1 for i in (1, 2, 3)
    )  # trajectories 0 and 4 are held out (seed 0)
    noisy = dataclasses.replace(cfg, ensemble_sources=["expert_noisy"], ensemble_steps=5)
    assert noisy.run_dir().name == "seed0_ens-expert_noisy"
    parts = load_world_model(train_world_model(noisy))
    assert parts.metrics["ensemble_windows"] == sum(
        len(collected.trajectory(i)) - 1 for i in (2, 3)
    )  # the noisy experts'
    with pytest.raises(ValueError, match="no source \\['teleop'\\]"):
        train_world_model(dataclasses.replace(cfg, ensemble_sources=["teleop"]))
    with pytest.raises(ValueError, match="no training trajectory of the sources \\['still'\\]"):
        train_world_model(dataclasses.replace(cfg, ensemble_sources=["still"]))


def test_a_data_subset_trains_on_fewer_trajectories_and_keeps_the_held_out_ones(trained_world_model, collected):
    from torchrl_dalir.training.world_model import keep_trajectories, split_trajectories

    cfg, path, _ = trained_world_model
    held = split_trajectories(collected.num_trajectories, cfg.held_out_fraction, cfg.seed)
    assert held.nonzero().flatten().tolist() == [0, 4]
    one, two = keep_trajectories(held, 1, 0), keep_trajectories(held, 2, 0)
    assert (one.sum(), two.sum()) == (1, 2) and (one <= two).all() and not (two & held).any()  # nested, never held out
    assert torch.equal(keep_trajectories(held, 0, 0), ~held)  # 0: every training trajectory
    with pytest.raises(ValueError, match="only 3 training trajectories"):
        keep_trajectories(held, 4, 0)
    small = dataclasses.replace(cfg, mixed_trajectories=1, ensemble_steps=5)
    assert small.run_dir().name == "seed0_mixed1"
    parts = load_world_model(train_world_model(small))
    (kept,) = one.nonzero().flatten().tolist()
    assert parts.metrics["ensemble_windows"] == len(collected.trajectory(kept)) - 1  # the one kept trajectory's windows
    assert parts.held_out_trajectories == [0, 4]
    assert parts.metrics["held_out_rows"] == load_world_model(path).metrics["held_out_rows"]  # the same held-out set
    with pytest.raises(ValueError, match="mixed_trajectories"):
        dataclasses.replace(cfg, mixed_trajectories=-1)
