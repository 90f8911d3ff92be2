"""Bad input is refused up front, with a message that names it and says what to change (issue 15)."""

import importlib.util
import pathlib
import re
import runpy
import sys
import warnings
from dataclasses import asdict

import numpy as np
import pytest
import torch
from conftest import SHORT_REACH
from tensordict import TensorDict

from torchrl_dalir import RerankingActor, keys, make_env
from torchrl_dalir.checkpoints import load_policy, load_world_model
from torchrl_dalir.config import parse_config
from torchrl_dalir.data.config import PRESETS as COLLECTION_PRESETS
from torchrl_dalir.data.config import CollectionConfig
from torchrl_dalir.envs import gym_env
from torchrl_dalir.evaluation import compare
from torchrl_dalir.evaluation.success_rate import evaluate
from torchrl_dalir.modules import (
    LatentEncoder,
    LatentEncoderModule,
    LatentWorldModel,
    PolicyConfig,
    ScorerEnsemble,
    ScorerModule,
    TaskCompletionScorer,
    WorldModelModule,
    make_policy,
)
from torchrl_dalir.pipeline import PRESETS, PipelineConfig
from torchrl_dalir.reranking import PointDropout
from torchrl_dalir.reranking.candidates import DropoutPolicy
from torchrl_dalir.seeds import eval_episode_seed
from torchrl_dalir.training import POLICY_PRESETS, PolicyTrainingConfig
from torchrl_dalir.training.loop import OptimConfig, fit
from torchrl_dalir.utils import weights_digest

EXAMPLES = pathlib.Path(__file__).parents[1] / "examples"
TINY = dict(down_dims=[16, 32, 64], point_hidden=[16, 32, 64], train_timesteps=20, ddim_steps=2, euler_steps=2)


# -- environments -------------------------------------------------------------------------------
@pytest.mark.parametrize(("setting", "value"), [("num_points", 0), ("num_points", -5), ("history", 0)])
def test_make_env_refuses_non_positive_sizes(setting, value):
    with pytest.raises(ValueError, match=f"{setting} must be at least 1, got {value}"):
        make_env(SHORT_REACH, **{setting: value})


def test_more_points_than_the_crop_holds_warns_with_the_distinct_count(monkeypatch):
    monkeypatch.setattr(gym_env, "_WARNED_REPEATS", set())
    with pytest.warns(
        UserWarning, match=r"reach: the crop box holds (\d+) distinct points .* num_points=20000"
    ) as record:
        env = make_env(SHORT_REACH, num_points=20000)  # (seeding resets: the first observation)
        cloud = env.reset()[keys.POINT_CLOUD]
    distinct = int(re.search(r"holds (\d+) distinct", str(record[0].message))[1])
    assert cloud.shape == (20000, 3)
    assert len(np.unique(cloud.numpy(), axis=0)) == pytest.approx(distinct, rel=0.1)  # another episode: about as many
    again = make_env(SHORT_REACH, num_points=20000)
    with warnings.catch_warnings(record=True) as later:
        warnings.simplefilter("always")
        again.reset()
    assert not [w for w in later if "distinct points" in str(w.message)]  # once per task and size in a process
    env.close(), again.close()


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_env_refuses_a_non_finite_action(bad):
    env = make_env(SHORT_REACH, render=False)
    td = env.reset()
    td[keys.ACTION] = torch.tensor([0.1, bad, 0.0, 0.0])
    with pytest.raises(ValueError, match="holds NaN or infinite values: check what the policy outputs"):
        env.step(td)
    env.close()


# -- policies, DALI-R's actor, point dropout ----------------------------------------------------
def _policy(seed=0, **key_names):
    torch.manual_seed(seed)
    policy = make_policy(PolicyConfig(kind="fm", **TINY), action_dim=4, state_dim=4, **key_names)
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 2 - 1)
    return policy.eval()


def _actor(policy, **kwargs):
    encoder = LatentEncoder.from_policy(policy)
    world_model = LatentWorldModel(encoder.latent_dim, 4, 8, hidden=32, layers=1, heads=2)
    return RerankingActor(
        policy, encoder, world_model, TaskCompletionScorer(encoder.latent_dim, hidden=32), num_candidates=3, **kwargs
    )


def _observation(batch=2, points=16, cloud=None):
    g = torch.Generator().manual_seed(3)
    cloud = torch.rand(batch, 2, points, 3, generator=g) if cloud is None else cloud
    return TensorDict({keys.POINT_CLOUD: cloud, keys.AGENT_POS: torch.rand(batch, 2, 4, generator=g)}, [batch])


BAD_OBSERVATIONS = {
    "no points": (_observation(points=0), r"point_cloud \(2, 2, 0, 3\) holds no points"),
    "empty batch": (_observation(batch=0), r"no observation to act on: point_cloud is \(0, 2, 16, 3\), an empty batch"),
    "NaN": (
        _observation(cloud=torch.full((2, 2, 16, 3), float("nan"))),
        r"point_cloud \(2, 2, 16, 3\) holds 192 NaN or infinite",
    ),
    "huge": (
        _observation(cloud=torch.full((2, 2, 16, 3), 1e30)),
        r"point_cloud \(2, 2, 16, 3\) lies far outside .* metres",
    ),
    "millimetres": (
        _observation(cloud=torch.rand(2, 2, 16, 3) * 1000),
        "lies far outside the points the policy was trained on",
    ),
    "integers": (
        _observation(cloud=torch.ones(2, 2, 16, 3, dtype=torch.long)),
        r"point_cloud \(2, 2, 16, 3\) is torch.int64: pass floating",
    ),
}


@pytest.mark.parametrize("actor", ["policy", "dalir", "dropout policy"])
@pytest.mark.parametrize("case", list(BAD_OBSERVATIONS))
def test_policies_and_actors_refuse_bad_observations_naming_key_and_shape(actor, case):
    policy = _policy()
    module = {"policy": policy, "dalir": _actor(policy), "dropout policy": DropoutPolicy(policy)}[actor]
    observation, message = BAD_OBSERVATIONS[case]
    with pytest.raises(ValueError, match=message):
        module(observation.clone())


@pytest.mark.parametrize("actor", ["policy", "dalir", "dropout policy"])
@pytest.mark.parametrize("missing", [keys.POINT_CLOUD, keys.AGENT_POS])
def test_a_missing_observation_key_is_refused_by_name(actor, missing):
    policy = _policy()
    module = {"policy": policy, "dalir": _actor(policy), "dropout policy": DropoutPolicy(policy)}[actor]
    with pytest.raises(KeyError, match=f"reads '{missing}', which the tensordict lacks"):
        module(_observation().exclude(missing))


@pytest.mark.parametrize(
    ("module", "given"),
    [
        (lambda e: LatentEncoderModule(e), {keys.POINT_CLOUD: torch.rand(2, 16, 3)}),
        (lambda e: WorldModelModule(LatentWorldModel(e.latent_dim, 4, 8, hidden=32, layers=1, heads=2)), {}),
        (lambda e: ScorerModule(TaskCompletionScorer(e.latent_dim, hidden=32)), {keys.LATENT: torch.rand(2, 128)}),
    ],
    ids=["encoder", "world model", "scorer"],
)
def test_the_imagination_modules_refuse_a_missing_in_key_by_name(module, given):
    module = module(LatentEncoder.from_policy(_policy()))
    missing = [k for k in module.in_keys if k not in given]
    with pytest.raises(KeyError, match=f"{type(module).__name__} reads '{missing[0]}'"):
        module(TensorDict(given, [2]))


def test_an_empty_dp3_store_is_refused_by_name(tmp_path):
    from torchrl_dalir.data.dp3_zarr import write_dp3_zarr

    with pytest.raises(ValueError, match="no episode to write"):
        write_dp3_zarr(tmp_path / "empty.zarr", [])
    assert not (tmp_path / "empty.zarr").exists()  # refused before anything is written


def test_the_message_names_the_policys_own_keys():
    policy = _policy(in_keys=[("obs", "cloud"), ("obs", "state")])
    observation = _observation(points=0)
    td = TensorDict({"obs": {"cloud": observation[keys.POINT_CLOUD], "state": observation[keys.AGENT_POS]}}, [2])
    with pytest.raises(ValueError, match=re.escape("('obs', 'cloud') (2, 2, 0, 3) holds no points")):
        policy(td)


@pytest.mark.parametrize("actor", ["policy", "dalir"])
def test_float64_observations_are_cast_to_the_policys_float32(actor):
    """numpy gives float64: the policy acts on it as on the same values in float32."""
    policy = _policy()
    module = policy if actor == "policy" else _actor(policy)
    observation = _observation()
    chunks = []
    for td in (observation.clone(), observation.apply(lambda x: x.double())):
        torch.manual_seed(0)
        if actor == "dalir":
            module.reset()
        chunks.append(module(td)[keys.ACTION_CHUNK])
    assert chunks[1].dtype == torch.float32
    torch.testing.assert_close(chunks[0], chunks[1], rtol=0, atol=0)


def test_point_dropout_refuses_empty_and_non_finite_clouds_and_keeps_float64():
    dropout = PointDropout(0.2)
    with pytest.raises(ValueError, match=r"point_cloud \(4, 0, 3\) holds no points"):
        dropout(TensorDict({keys.POINT_CLOUD: torch.rand(4, 0, 3)}, [4]))
    cloud = torch.rand(4, 10, 3)
    cloud[1, 2, 0] = float("inf")
    with pytest.raises(ValueError, match=r"point_cloud \(4, 10, 3\) holds 1 NaN or infinite values"):
        dropout(TensorDict({keys.POINT_CLOUD: cloud}, [4]))
    out = dropout(TensorDict({keys.POINT_CLOUD: torch.rand(4, 10, 3, dtype=torch.float64)}, [4]))[keys.POINT_CLOUD]
    assert out.dtype == torch.float64 and out.shape == (4, 10, 3)  # a transform keeps the cloud's dtype


def _nan_parameter(module):
    with torch.no_grad():
        next(module.parameters()).fill_(float("nan"))


@pytest.mark.parametrize("actor", ["policy", "dalir", "dropout policy"])
def test_a_finite_observation_that_overflows_the_policy_is_refused_not_acted_on(actor):
    """A robot state of 1e30 is finite (not refused as input) but overflows the network into NaN actions: the
    chunk is refused, naming the likely cause, instead of being executed (MuJoCo would reset) or scored."""
    policy = _policy()
    module = {"policy": policy, "dalir": _actor(policy), "dropout policy": DropoutPolicy(policy)}[actor]
    observation = _observation()
    observation[keys.AGENT_POS] = torch.full((2, 2, 4), 1e30)
    message = (
        r"action_chunk \(\d+, 16, 4\) holds \d+ NaN or infinite values: .* overflowed the network: "
        r"most likely its robot state \(agent_pos"
    )
    with pytest.raises(ValueError, match=message):
        module(observation)


def test_a_policy_with_nan_weights_names_its_weights():
    policy = _policy()
    _nan_parameter(policy.unet)
    with pytest.raises(
        ValueError, match=r"action_chunk \(2, 16, 4\) holds 128 NaN .* the policy's weights or normalizers hold NaN"
    ):
        policy(_observation())


def test_dalir_refuses_nan_scores_instead_of_ranking_them():
    actor = _actor(_policy())
    _nan_parameter(actor.scorer)
    with pytest.raises(
        ValueError, match=r"DALI-R's candidate_scores \(2, 1, 3\) holds 6 NaN or infinite values: .* world model"
    ):
        actor(_observation())


# -- checkpoints ---------------------------------------------------------------------------------
def _save_policy(policy, path, task="reach"):
    """A policy checkpoint as ``train_policy`` writes it (the entries ``load_policy`` reads)."""
    torch.save(
        {
            "kind": "policy",
            "task": task,
            "policy_config": asdict(policy.config),
            "action_dim": policy.action_dim,
            "state_dim": policy.state_dim,
            "num_points": 16,
            "policy_state": policy.state_dict(),
        },
        path,
    )
    return path


def _save_world_model(policy_path, path, digest=True):
    """A world-model checkpoint on top of the policy at ``policy_path``, as ``train_world_model`` writes it."""
    policy = load_policy(policy_path)
    actor = _actor(policy)
    ensemble = ScorerEnsemble(actor.encoder.latent_dim, 16, 2)
    state = {
        "kind": "world_model",
        "task": policy.task,
        "policy_checkpoint": str(policy_path),
        "policy_config": asdict(policy.config),
        "action_dim": 4,
        "state_dim": 4,
        "world_model_args": dict(
            latent_dim=actor.encoder.latent_dim, action_dim=4, action_steps=8, hidden=32, layers=1, heads=2
        ),
        "scorer_hidden": 32,
        "encoder_state": actor.encoder.state_dict(),
        "scorer_state": actor.scorer.state_dict(),
        "world_model_state": actor.world_model.state_dict(),
        "ensemble_args": dict(latent_dim=actor.encoder.latent_dim, hidden=16, members=2),
        "ensemble_state": ensemble.state_dict(),
        "metrics": {},
        "held_out_trajectories": [],
    }
    if digest:
        state["policy_digest"] = weights_digest(policy)
    torch.save(state, path)
    return path


def test_a_checkpoint_missing_an_entry_names_the_file_and_the_entry(tmp_path):
    path = _save_policy(_policy(), tmp_path / "policy.pt")
    state = torch.load(path, weights_only=True)
    torch.save({k: v for k, v in state.items() if k != "num_points"}, tmp_path / "no_size.pt")
    with pytest.raises(
        ValueError,
        match=re.escape(
            f"{tmp_path / 'no_size.pt'} is a damaged or incomplete policy checkpoint: it has no 'num_points' entry"
        ),
    ):
        load_policy(tmp_path / "no_size.pt")
    weights = dict(state["policy_state"])
    weights.pop(next(iter(weights)))
    torch.save({**state, "policy_state": weights}, tmp_path / "no_weight.pt")
    with pytest.raises(
        ValueError, match=re.escape(f"{tmp_path / 'no_weight.pt'}: the weights in 'policy_state' do not fit")
    ):
        load_policy(tmp_path / "no_weight.pt")
    wm = torch.load(_save_world_model(path, tmp_path / "world_model.pt"), weights_only=True)
    torch.save({k: v for k, v in wm.items() if k not in ("scorer_state", "metrics")}, tmp_path / "no_scorer.pt")
    with pytest.raises(
        ValueError,
        match=(
            "no_scorer.pt is a damaged or incomplete world_model checkpoint: "
            "it has no 'scorer_state', 'metrics' entries"
        ),
    ):
        load_world_model(tmp_path / "no_scorer.pt")


def _fit(path, num_steps=2):
    from torchrl.objectives import LossModule

    model = torch.nn.Linear(2, 1)

    class Loss(LossModule):
        def forward(self, batch):
            return TensorDict({"loss": model(batch["x"]).pow(2).mean()}, [])

    return fit(
        Loss(),
        model,
        lambda g: TensorDict({"x": torch.rand(4, 2, generator=g)}, [4]),
        num_steps,
        OptimConfig(warmup_steps=0),
        path,
        lambda ema: {},
        progress=False,
    )


def test_a_damaged_checkpoint_at_the_resume_path_is_named_with_what_to_do(tmp_path):
    path = tmp_path / "run" / "checkpoint.pt"
    _fit(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(
        ValueError,
        match=f"cannot resume training: {re.escape(str(path))} is not a torchrl_dalir training checkpoint, "
        f"or is truncated.*delete {re.escape(str(path))}",
    ):
        _fit(path, num_steps=4)
    path.unlink()
    _fit(path)
    state = torch.load(path, weights_only=True)
    del state["optimizer"]
    torch.save(state, path)
    with pytest.raises(
        ValueError,
        match=(
            "cannot resume training: .*checkpoint.pt is a damaged or incomplete training checkpoint: "
            "it has no 'optimizer'"
        ),
    ):
        _fit(path, num_steps=4)
    with pytest.raises(ValueError, match="num_steps must be at least 0, got -1"):
        _fit(tmp_path / "other.pt", num_steps=-1)  # an untrained checkpoint would count as finished
    assert not (tmp_path / "other.pt").exists()


# -- settings ------------------------------------------------------------------------------------
def _example_config(name):
    """The ``Config`` of ``examples/[<tier>/]<name>.py``, imported as a module (so its annotations resolve)."""
    (path,) = EXAMPLES.glob(f"**/{name}.py")
    spec = importlib.util.spec_from_file_location(f"example_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module.Config


@pytest.mark.parametrize(
    ("job", "argv", "message"),
    [
        ("collection", ["chunk_size=0"], "chunk_size must be at least 1, got 0"),
        ("main", ["collection.chunk_size=0"], "chunk_size must be at least 1, got 0"),
        ("main", ["eval_episodes=0"], "eval_episodes must be at least 1, got 0"),
        ("main", ["num_candidates=0"], "num_candidates must be at least 1, got 0"),
        ("main", ["eval_seed=-1"], "eval_seed must be at least 0, got -1: .*data-generation seeds"),
        ("main", ["calibration_seed=-100000"], "calibration_seed must be at least 0"),
        ("main", ["dropout=1.0"], r"dropout must lie in \[0, 1\), got 1.0"),
        ("main", ["calibration_episodes=-1"], "calibration_episodes must be at least 0"),
        ("main", ["policy_training.batch_size=0"], "batch_size must be at least 1, got 0"),
        ("main", ["policy_training.num_steps=-1"], "num_steps must be at least 0, got -1"),
        ("main", ["world_model.wm_batch_size=0"], "wm_batch_size must be at least 1, got 0"),
        ("main", ["world_model.ensemble_steps=-5"], "ensemble_steps must be at least 0, got -5"),
        ("policy", ["epochs=0"], "epochs must be at least 1, got 0"),
        ("evaluate", ["episodes=0"], "episodes must be at least 1, got 0"),
        ("evaluate", ["episodes=-3"], "episodes must be at least 1, got -3"),
        ("evaluate", ["num_candidates=0"], "num_candidates must be at least 1, got 0"),
        ("evaluate", ["seed=-1"], "seed must be at least 0, got -1"),
        ("calibrate_selection", ["test_seed=-2"], "test_seed must be at least 0"),
        ("diagnose_reranking", ["episodes=0"], "episodes must be at least 1"),
        ("train_policy", ["eval_seed=-1"], "eval_seed must be at least 0"),
    ],
)
def test_bad_settings_are_refused_when_the_configuration_is_read(job, argv, message):
    config, presets = {
        "collection": (CollectionConfig, COLLECTION_PRESETS),
        "main": (PipelineConfig, PRESETS),
        "policy": (PolicyTrainingConfig, POLICY_PRESETS),
    }.get(job, (None, None))
    if config is None:
        config = _example_config(job)
        presets = POLICY_PRESETS if job == "train_policy" else None
    with pytest.raises(ValueError, match=message):
        parse_config(config, argv, presets)


def test_negative_evaluation_seeds_are_refused_by_the_library():
    assert eval_episode_seed(0, 0) == 1_000_000_000
    with pytest.raises(ValueError, match="evaluation seed must be at least 0, got -1"):
        eval_episode_seed(-1, 0)
    with pytest.raises(ValueError, match="num_episodes must be at least 1, got 0"):
        evaluate(None, "reach", 0)


@pytest.mark.parametrize("chunk_size", [0, -2])
def test_collect_refuses_a_chunk_size_below_one_before_writing(chunk_size, tmp_path):
    from torchrl_dalir.data import Source, collect

    with pytest.raises(ValueError, match=f"chunk_size must be at least 1, got {chunk_size}"):
        collect(SHORT_REACH, tmp_path / "reach", [Source("expert", 1)], chunk_size=chunk_size, progress=False)
    assert not (tmp_path / "reach").exists()


@pytest.mark.parametrize("script", ["evaluate", "calibrate_selection"])
def test_a_bad_output_folder_is_refused_before_any_episode(script, tmp_path, monkeypatch):
    from torchrl_dalir.evaluation import calibration

    (tmp_path / "file").write_text("")
    for module, name in ((compare, "evaluate_checkpoints"), (calibration, "calibrate")):
        monkeypatch.setattr(
            module, name, lambda *a, **k: pytest.fail("episodes ran before the output folder was checked")
        )
    monkeypatch.setattr(sys, "argv", [f"{script}.py", f"out={tmp_path / 'file' / 'results'}"])
    with pytest.raises(
        ValueError,
        match=re.escape(f"cannot write results to the folder {tmp_path / 'file' / 'results'}") + ".*pass out=",
    ):
        runpy.run_path(str(EXAMPLES / f"{script}.py"), run_name="__main__")


# -- the world model belongs to one policy -------------------------------------------------------
def test_a_world_model_is_refused_with_another_policy_of_the_same_task(tmp_path, monkeypatch):
    policy_a = _save_policy(_policy(seed=0), tmp_path / "a.pt")
    policy_b = _save_policy(_policy(seed=1), tmp_path / "b.pt")
    wm = _save_world_model(policy_a, tmp_path / "world_model_a.pt")
    assert RerankingActor.from_checkpoints(policy_a, wm, num_candidates=2).policy.checkpoint == str(policy_a)
    assert load_world_model(wm).policy_digest == weights_digest(load_policy(policy_a))
    both = (
        f"the world model at {re.escape(str(wm))} was trained on top of the policy at {re.escape(str(policy_a))}, "
        f"not on the policy at {re.escape(str(policy_b))}"
    )
    with pytest.raises(ValueError, match=both):
        RerankingActor.from_checkpoints(policy_b, wm)
    monkeypatch.setattr(compare, "evaluate", lambda *a, **k: pytest.fail("an episode ran"))
    with pytest.raises(ValueError, match=both):  # before the base policy's episodes
        compare.evaluate_checkpoints(policy_b, wm, methods=["base", "dalir"], progress=False)
    old = _save_world_model(policy_a, tmp_path / "old.pt", digest=False)
    with pytest.warns(UserWarning, match=f"{re.escape(str(old))} does not record which policy it was trained on"):
        RerankingActor.from_checkpoints(policy_b, old, num_candidates=2)


def test_the_digest_is_the_weights_not_the_object():
    a, b = _policy(seed=0), _policy(seed=0)
    assert weights_digest(a) == weights_digest(b)
    with torch.no_grad():
        next(b.parameters()).view(-1)[0] += 1e-6
    assert weights_digest(a) != weights_digest(b)
