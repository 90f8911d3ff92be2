"""DALI-R on a policy of the user's own (issue 40, part 4): the ChunkPolicy interface, point dropout
without per-point features, a world model trained on top of a policy object, and a TorchRL rollout.

The user's policy is the one of the README's "Wrap your own policy" section, executed here: what
users read is what is tested."""

import dataclasses
import re
from pathlib import Path

import pytest
import torch
from conftest import SHORT_REACH
from tensordict import TensorDict
from test_dropin import check_receding_horizon

from torchrl_dalir import ChunkPolicy, RerankingActor, RerankingConfig, keys, make_env, receding_horizon
from torchrl_dalir.checkpoints import load_world_model, safe_torch_load
from torchrl_dalir.config import parse_config
from torchrl_dalir.modules import LatentEncoder, LatentWorldModel, PolicyConfig, TaskCompletionScorer, make_policy
from torchrl_dalir.reranking import CANDIDATE_SCORES, CHOSEN_CANDIDATE, PointDropout, SearchConfig
from torchrl_dalir.reranking.candidates import DropoutPolicy
from torchrl_dalir.training import WORLD_MODEL_PRESETS, WorldModelTrainingConfig, train_world_model
from torchrl_dalir.utils import weights_digest

ROOT = Path(__file__).resolve().parent.parent
MARK = "<!-- tested: own-policy -->"
SOURCES = [ROOT / "README.md"]


def _blocks() -> list[tuple[Path, str]]:
    """Every python block marked ``MARK`` in the README's "Wrap your own policy"."""
    found = [
        (path, block)
        for path in SOURCES
        if path.exists()
        for block in re.findall(rf"{re.escape(MARK)}\n```python\n(.*?)```", path.read_text(), flags=re.S)
    ]
    assert found, f"no python block marked {MARK} in {[str(p) for p in SOURCES]}"
    return found


def _run(path: Path, block: str) -> dict:
    namespace = {"__name__": "own_policy_snippet"}
    exec(compile(block, str(path), "exec"), namespace)
    return namespace


@pytest.fixture(scope="module")
def snippet() -> dict:
    return _run(*_blocks()[0])


def _policy(snippet, seed=0):
    torch.manual_seed(seed)
    return snippet["MyChunkPolicy"]()


def _observation(batch=2, points=64):
    g = torch.Generator().manual_seed(5)
    return TensorDict(
        {
            keys.POINT_CLOUD: torch.rand(batch, 2, points, 3, generator=g),
            keys.AGENT_POS: torch.rand(batch, 2, 4, generator=g),
        },
        [batch],
    )


def _untrained_parts(action_dim=4, state_dim=4):
    torch.manual_seed(1)
    encoder = LatentEncoder.fresh(state_dim, point_hidden=[16, 32], point_out=16, state_out=16)
    world_model = LatentWorldModel(encoder.latent_dim, action_dim, 8, hidden=32, layers=1, heads=2)
    torch.nn.init.normal_(world_model.out[-1].weight, std=0.1)
    return encoder, world_model, TaskCompletionScorer(encoder.latent_dim, hidden=32)


def test_the_snippet_runs_as_written():
    for path, block in _blocks():
        namespace = _run(path, block)
        policy, decision = namespace["policy"], namespace["decision"]
        assert isinstance(policy, ChunkPolicy)
        library_classes = [cls for cls in type(policy).__mro__ if cls.__module__.startswith("torchrl_dalir")]
        assert library_classes == []  # the user's policy subclasses none of the library's classes
        assert decision[keys.ACTION_CHUNK].shape == (3, 16, 4) and decision[CANDIDATE_SCORES].shape == (3, 8)
        assert torch.equal(decision[CHOSEN_CANDIDATE], decision[CANDIDATE_SCORES].argmax(-1))


def test_the_actor_names_what_a_policy_lacks(snippet):
    parts = _untrained_parts()
    with pytest.raises(
        TypeError,
        match=r"RerankingActor needs a chunk policy .*object has no 'encode', 'sample', 'obs_steps', 'horizon'",
    ):
        RerankingActor(object(), *parts)
    policy = _policy(snippet)
    policy.sample = None  # not callable
    with pytest.raises(TypeError, match="MyChunkPolicy has no 'sample'"):
        RerankingActor(policy, *parts)
    policy = _policy(snippet)
    policy.action_steps = 16  # entries 1 .. 16 of a 16-action chunk
    with pytest.raises(ValueError, match="beyond its horizon"):
        RerankingActor(policy, *parts)
    with pytest.raises(
        ValueError, match="has no point_normalizer, point_encoder, state_normalizer, state_encoder to copy"
    ):
        LatentEncoder.from_policy(_policy(snippet))


def test_point_dropout_encodes_each_dropped_cloud_without_per_point_features(snippet):
    policy, obs = _policy(snippet), _observation()
    cloud, agent_pos = obs[keys.POINT_CLOUD], obs[keys.AGENT_POS]
    dropout = PointDropout(0.3)
    cond = dropout.conditions(policy, cloud, agent_pos, 6, torch.Generator().manual_seed(1))
    keep = dropout.keep_masks((2, 6, 2, 64), torch.Generator().manual_seed(1))
    keep[:, 0] = True
    assert cond.shape == (2, 6, policy.encode(cloud, agent_pos).shape[-1])
    torch.testing.assert_close(cond[:, 0], policy.encode(cloud, agent_pos))  # candidate 0: the clean observation
    for b in range(2):
        for c in range(1, 6):  # the kept points of each frame (a max-pooled encoder sees the set)
            kept = [cloud[b, f][keep[b, c, f]] for f in range(2)]
            expected = torch.cat([torch.cat([policy.points(kept[f]).max(0).values, agent_pos[b, f]]) for f in range(2)])
            torch.testing.assert_close(cond[b, c], expected)
    assert not torch.allclose(cond[:, 1], cond[:, 0])


def test_both_paths_of_point_dropout_agree_on_the_librarys_policy():
    torch.manual_seed(0)
    policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]), action_dim=4, state_dim=4)
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 2 - 1)

    class EncodeOnly:  # the policy's ChunkPolicy members, without point_features and condition
        obs_steps, horizon, action_steps, action_dim = 2, 16, 8, 4
        encode, sample = policy.encode, policy.sample

    obs = _observation(batch=3, points=40)
    fast, slow = (
        PointDropout(0.2).conditions(p, obs[keys.POINT_CLOUD], obs[keys.AGENT_POS], 8, torch.Generator().manual_seed(2))
        for p in (policy, EncodeOnly())
    )
    torch.testing.assert_close(slow, fast, rtol=1e-5, atol=1e-5)


def test_search_and_the_dropout_policy_work_without_the_optional_members(snippet):
    policy, obs = _policy(snippet), _observation()
    parts = _untrained_parts()
    parts[1].action_normalizer.fit(torch.rand(100, 4) * 2 - 1)  # the world model's, the search's space for this policy
    dalir = RerankingActor(
        policy,
        *parts,
        config=RerankingConfig(num_candidates=4, candidates="clean", search=SearchConfig("shooting", iterations=2)),
    )
    assert dalir.search_normalizer() is parts[1].action_normalizer
    chunks = dalir.sample_candidates(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS])
    assert chunks.shape == (2, 4, 16, 4) and not torch.equal(
        chunks[:, 1:, 1:9], chunks[:, :1, 1:9].expand(-1, 3, -1, -1)
    )
    out = DropoutPolicy(policy, 0.2, seed=3)(obs.clone())
    assert out[keys.ACTION_CHUNK].shape == (2, 16, 4) and torch.equal(out[keys.POINT_CLOUD], obs[keys.POINT_CLOUD])


def test_a_world_model_trained_on_a_policy_object_drives_dalir_in_a_rollout(snippet, collected, tmp_path):
    policy = _policy(snippet)
    data = tmp_path / "data"
    (data / "reach").mkdir(parents=True)
    (data / "reach" / "mixed").symlink_to(collected.root)
    settings = ["preset=smoke", "task=reach", f"data={data}", f"out={tmp_path / 'world_models'}", "progress=false"]
    cfg = parse_config(WorldModelTrainingConfig, settings, WORLD_MODEL_PRESETS)
    with pytest.raises(ValueError, match="encoder=frozen keeps the policy's own encoders"):
        train_world_model(dataclasses.replace(cfg, encoder="frozen"), policy)
    path = train_world_model(cfg, policy)
    assert train_world_model(cfg, policy) == path  # finished: not trained again

    parts = load_world_model(path, policy=policy)
    state = safe_torch_load(path)
    assert (parts.task, parts.policy_digest, state["policy_config"]) == ("reach", weights_digest(policy), None)
    assert (
        parts.policy_checkpoint.startswith("MyChunkPolicy object")
        and state["config"]["policy_checkpoint"] == parts.policy_checkpoint
    )
    assert parts.encoder.architecture() == LatentEncoder.fresh(4).architecture() == state["encoder_args"]
    assert bool(parts.encoder.point_normalizer.fitted) and parts.world_model.action_steps == policy.action_steps
    again = load_world_model(path, policy=policy)
    for name in ("encoder", "world_model", "scorer", "ensemble"):
        loaded, reloaded = getattr(parts, name).state_dict(), getattr(again, name).state_dict()
        assert loaded.keys() == reloaded.keys() and all(torch.equal(loaded[k], reloaded[k]) for k in loaded), name
    with pytest.raises(ValueError, match="whose weights differ"):
        RerankingActor.on_policy(_policy(snippet, seed=1), path)

    dalir = RerankingActor.on_policy(policy, path, config=RerankingConfig(num_candidates=4, common_noise=True), seed=2)
    assert (dalir.num_candidates, dalir.selection.name, dalir.common_noise) == (4, "argmax(state)", True)
    obs = _observation()
    cloud, agent_pos = obs[keys.POINT_CLOUD], obs[keys.AGENT_POS]
    torch.manual_seed(7)
    chunks, scores = dalir.propose(cloud, agent_pos)
    torch.manual_seed(7)
    own = policy.sample(policy.encode(cloud, agent_pos))  # the policy's own sample, under the same global seed
    assert chunks.shape == (2, 4, 16, 4) and scores.shape == (2, 4)
    assert torch.equal(chunks[:, 0], own)  # common noise: candidate 0 is the policy's own chunk, bit for bit
    assert ((scores >= 0) & (scores <= 1)).all()

    env = make_env(dataclasses.replace(SHORT_REACH, max_steps=30), num_points=64, history=2, seed=0)
    try:
        actor = receding_horizon(dalir, env=env)  # the chunk sizes come from the policy
        assert (actor.obs_steps, actor.action_steps) == (2, 8)
        rollout = env.rollout(20, actor, break_when_any_done=False)
        assert rollout[keys.ACTION].shape == (20, 4) and rollout[CANDIDATE_SCORES].shape == (20, 4)
        check_receding_horizon(
            rollout
        )  # replans every 8 steps; the executed action is the plan's, the choice the arg-max
        assert rollout[keys.ACTION].abs().max() <= 1
        assert env.rollout(9, receding_horizon(policy))[keys.ACTION].shape == (9, 4)  # the user's policy alone, too
    finally:
        env.close()
