"""The latent encoder, world model and scorers as TensorDict modules (issue 16, item 1)."""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential

from torchrl_dalir import keys
from torchrl_dalir.modules import (
    LatentEncoder,
    LatentEncoderModule,
    LatentWorldModel,
    PolicyConfig,
    ScorerEnsemble,
    ScorerEnsembleModule,
    ScorerModule,
    TaskCompletionScorer,
    WorldModelModule,
    make_policy,
)


def _tiny_parts():
    torch.manual_seed(0)
    policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]), action_dim=4, state_dim=4)
    encoder = LatentEncoder.from_policy(policy).eval()
    world_model = LatentWorldModel(encoder.latent_dim, 4, hidden=32, layers=1, heads=2).eval()
    torch.nn.init.normal_(world_model.out[-1].weight, std=0.1)  # untrained, it would predict "no change"
    scorer = TaskCompletionScorer(encoder.latent_dim, hidden=32).eval()
    ensemble = ScorerEnsemble(encoder.latent_dim, hidden=16, members=3).eval()
    observation = {
        keys.POINT_CLOUD: torch.rand(5, 40, 3),
        keys.AGENT_POS: torch.rand(5, 4),
        keys.ACTION_CHUNK: torch.rand(5, 8, 4) * 2 - 1,
    }
    return encoder, world_model, scorer, ensemble, observation


@torch.no_grad()
def test_the_sequential_of_the_modules_equals_the_tensor_level_path_exactly():
    encoder, world_model, scorer, ensemble, obs = _tiny_parts()
    imagine = TensorDictSequential(
        LatentEncoderModule(encoder),
        WorldModelModule(world_model),
        ScorerModule(scorer),
        ScorerEnsembleModule(ensemble),
    )
    assert imagine.in_keys == [keys.POINT_CLOUD, keys.AGENT_POS, keys.ACTION_CHUNK]
    assert imagine.out_keys == [keys.LATENT, keys.IMAGINED_LATENT, keys.COMPLETION_LOGIT, keys.MEMBER_LOGITS]
    td = imagine(TensorDict(obs, [5]))
    latent = encoder(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS])
    imagined = world_model.imagine(latent, obs[keys.ACTION_CHUNK])
    assert not torch.equal(imagined, latent)
    assert torch.equal(td[keys.LATENT], latent)
    assert torch.equal(td[keys.IMAGINED_LATENT], imagined)
    assert torch.equal(td[keys.COMPLETION_LOGIT], scorer(imagined))
    assert torch.equal(td[keys.MEMBER_LOGITS], ensemble(imagined).movedim(0, -1))  # [5, 3]: the members last
    # the modules share the tensor-level modules' parameters (a copy would not follow training)
    assert imagine[1].module is world_model and {id(p) for p in imagine.parameters()} >= {
        id(p) for p in scorer.parameters()
    }


@torch.no_grad()
def test_the_modules_read_and_write_the_keys_they_are_given():
    encoder, world_model, scorer, _, obs = _tiny_parts()
    imagine = TensorDictSequential(
        LatentEncoderModule(encoder, in_keys=[("obs", "cloud"), ("obs", "state")], out_keys=["s"]),
        WorldModelModule(world_model, in_keys=["s", "plan"], out_keys=["s_hat"]),
        ScorerModule(scorer, in_keys=["s_hat"], out_keys=[("dalir", "logit")]),
    )
    assert imagine.in_keys == [("obs", "cloud"), ("obs", "state"), "plan"]
    td = TensorDict(
        {"obs": {"cloud": obs[keys.POINT_CLOUD], "state": obs[keys.AGENT_POS]}, "plan": obs[keys.ACTION_CHUNK]}, [5]
    )
    renamed = imagine(td)
    default = TensorDictSequential(LatentEncoderModule(encoder), WorldModelModule(world_model), ScorerModule(scorer))(
        TensorDict(obs, [5])
    )
    assert torch.equal(renamed["dalir", "logit"], default[keys.COMPLETION_LOGIT])
    assert keys.LATENT not in renamed.keys() and keys.COMPLETION_LOGIT not in renamed.keys()
    # the state scorer on the current latent, as it was trained
    current = ScorerModule(scorer, in_keys=[keys.LATENT], out_keys=["state_logit"])(default)
    assert torch.equal(current["state_logit"], scorer(default[keys.LATENT]))
    with pytest.raises(ValueError, match="takes 2 in_keys"):
        WorldModelModule(world_model, in_keys=["s"])


@torch.no_grad()
def test_readme_snippet_builds_the_modules_from_a_checkpoint(trained_world_model):
    from torchrl_dalir import RerankingActor
    from torchrl_dalir.reranking.selection import SelectionConfig

    _, world_model_checkpoint, policy_path = trained_world_model
    B, cloud, agent_pos, actions = 3, torch.rand(3, 64, 3), torch.rand(3, 4), torch.rand(3, 8, 4) * 2 - 1
    # --- docs/guides/dalir.md snippet, verbatim ---
    from tensordict import TensorDict
    from tensordict.nn import TensorDictSequential

    from torchrl_dalir.checkpoints import load_world_model
    from torchrl_dalir.modules import LatentEncoderModule, ScorerModule, WorldModelModule

    parts = load_world_model(world_model_checkpoint)  # the latent encoder, world model and scorer of one run
    imagine = TensorDictSequential(
        LatentEncoderModule(parts.encoder), WorldModelModule(parts.world_model), ScorerModule(parts.scorer)
    )
    td = imagine(TensorDict(point_cloud=cloud, agent_pos=agent_pos, action_chunk=actions, batch_size=[B]))
    (
        td["latent"],
        td["imagined_latent"],
        td["completion_logit"],
    )  # s_t, s_hat_{t+k} and the scorer's logit of s_hat_{t+k}
    # --- end of the snippet ---
    actor = RerankingActor.from_checkpoints(
        policy_path, world_model_checkpoint, num_candidates=2, selection=SelectionConfig()
    )
    chunks = torch.zeros(B, 1, actor.policy.config.horizon, 4)
    chunks[:, :, actor.policy.config.executed] = actions[:, None]  # the executed actions of a 16-action chunk
    imagined = actor.imagine(cloud[:, None], agent_pos[:, None], chunks)[:, 0]  # what the actor scores
    assert torch.allclose(td["imagined_latent"], imagined, atol=1e-6)
    assert torch.allclose(
        torch.sigmoid(td["completion_logit"]), actor.score(cloud[:, None], agent_pos[:, None], chunks)[:, 0], atol=1e-6
    )
