"""Every loss follows TorchRL's ``set_keys`` contract: its inputs are the entries its ``_AcceptedKeys`` name."""

import dataclasses

import pytest
import torch
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.modules import (
    LatentEncoder,
    LatentWorldModel,
    PolicyConfig,
    ScorerEnsemble,
    TaskCompletionScorer,
    make_policy,
)
from torchrl_dalir.objectives import (
    ChunkGenerationLoss,
    ConsistencyFlowMatchingLoss,
    DiffusionLoss,
    FlowMatchingLoss,
    ImaginedCompletionLoss,
    KeyedLossModule,
    LatentDynamicsLoss,
    TaskCompletionLoss,
)

TINY = dict(down_dims=[16, 32, 64], point_hidden=[16, 32, 64], train_timesteps=20)


def _policy(kind):
    policy = make_policy(PolicyConfig(kind=kind, **TINY), action_dim=4, state_dim=4)
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 2 - 1)
    return policy


def _window():
    return TensorDict(
        {
            keys.POINT_CLOUD: torch.rand(4, 2, 16, 3),
            keys.AGENT_POS: torch.rand(4, 2, 4),
            keys.ACTION_CHUNK: torch.rand(4, 16, 4),
        },
        [4],
    )


def _rows(latent_dim):
    rows = {
        keys.POINT_CLOUD: torch.rand(6, 16, 3),
        keys.AGENT_POS: torch.rand(6, 4),
        keys.COMPLETION_TARGET: torch.rand(6),
    }
    return TensorDict({**rows, keys.LATENT: torch.randn(6, latent_dim)}, [6])


def _task_completion(frozen):
    encoder = LatentEncoder.from_policy(_policy("fm"))
    scorer = TaskCompletionScorer(encoder.latent_dim, hidden=16)
    return TaskCompletionLoss(None if frozen else encoder, scorer), _rows(encoder.latent_dim)


def _latent_dynamics():
    batch = TensorDict(
        {
            keys.LATENT: torch.randn(5, 16),
            keys.FUTURE: {keys.LATENT: torch.randn(5, 16)},
            keys.ACTION_CHUNK: torch.randn(5, 8, 4),
        },
        [5],
    )
    return LatentDynamicsLoss(LatentWorldModel(16, 4, hidden=16, layers=1, heads=2)), batch


def _imagined_completion():
    batch = TensorDict(
        {keys.IMAGINED_LATENT: torch.randn(3, 8, 16), keys.FUTURE: {keys.COMPLETION_TARGET: torch.rand(3, 8)}}, [3, 8]
    )
    return ImaginedCompletionLoss(ScorerEnsemble(16, hidden=16, members=3)), batch


# each loss, a batch it reads and the _AcceptedKeys names that loss reads
CASES = {
    "diffusion": (lambda: (DiffusionLoss(_policy("dp")), _window()), ("point_cloud", "agent_pos", "action_chunk")),
    "flow_matching": (
        lambda: (FlowMatchingLoss(_policy("fm")), _window()),
        ("point_cloud", "agent_pos", "action_chunk"),
    ),
    "consistency": (
        lambda: (ConsistencyFlowMatchingLoss(_policy("fm")), _window()),
        ("point_cloud", "agent_pos", "action_chunk"),
    ),
    "task_completion": (lambda: _task_completion(frozen=False), ("point_cloud", "agent_pos", "target")),
    "task_completion_frozen": (lambda: _task_completion(frozen=True), ("latent", "target")),
    "latent_dynamics": (_latent_dynamics, ("latent", "future_latent", "action_chunk")),
    "imagined_completion": (_imagined_completion, ("imagined_latent", "target")),
}


def _loss(loss_module, batch):
    torch.manual_seed(0)  # the same noise, steps and path times for every call
    (name,) = loss_module.out_keys
    return loss_module(batch)[name]


@pytest.fixture(params=list(CASES))
def case(request):
    torch.manual_seed(0)
    make, read = CASES[request.param]
    loss_module, batch = make()
    return loss_module, batch, read


def test_every_loss_declares_its_keys_with_defaults_from_the_keys_module(case):
    loss_module, _, read = case
    assert isinstance(loss_module, KeyedLossModule)
    assert loss_module.default_keys is type(loss_module)._AcceptedKeys
    defaults = {field.name: field.default for field in dataclasses.fields(loss_module._AcceptedKeys)}
    names = {value for name, value in vars(keys).items() if name.isupper() and isinstance(value, str)}
    for name, default in defaults.items():
        assert all(part in names for part in ((default,) if isinstance(default, str) else default)), (name, default)
    assert loss_module.in_keys == [getattr(loss_module.default_keys(), name) for name in read]


def test_a_renamed_key_is_read(case):
    loss_module, batch, read = case
    expected = _loss(loss_module, batch)
    for name in read:
        default = getattr(loss_module.tensor_keys, name)
        moved = batch.clone(recurse=False)
        moved["renamed", name] = moved.pop(default)
        with pytest.raises(KeyError, match=default if isinstance(default, str) else default[-1]):
            loss_module(moved)  # still reading the default entry, which is gone
        loss_module.set_keys(**{name: ("renamed", name)})
        assert ("renamed", name) in loss_module.in_keys and default not in loss_module.in_keys
        assert torch.equal(_loss(loss_module, moved), expected), name
        loss_module.set_keys(**{name: None})  # back to the default
        assert getattr(loss_module.tensor_keys, name) == default and default in loss_module.in_keys
    assert torch.equal(_loss(loss_module, batch), expected)


def test_an_unknown_key_name_is_refused(case):
    loss_module, _, _ = case
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss_module.set_keys(observation="point_cloud")


def test_task_completion_target_key_is_set_keys_shorthand():
    torch.manual_seed(0)
    loss_module, rows = _task_completion(frozen=True)
    rows["dense"] = torch.rand(6)
    shorthand = TaskCompletionLoss(None, loss_module.scorer, target_key="dense")
    assert shorthand.tensor_keys.target == "dense" and shorthand.in_keys == [keys.LATENT, "dense"]
    loss_module.set_keys(target="dense")
    assert torch.equal(_loss(shorthand, rows), _loss(loss_module, rows))
    assert not torch.equal(_loss(shorthand, rows), _loss(TaskCompletionLoss(None, loss_module.scorer), rows))


def test_generative_losses_share_one_skeleton():
    for loss_class in (DiffusionLoss, FlowMatchingLoss, ConsistencyFlowMatchingLoss):
        assert issubclass(loss_class, ChunkGenerationLoss)
        assert loss_class._AcceptedKeys is ChunkGenerationLoss._AcceptedKeys and "chunk_loss" in vars(loss_class)
