"""DALI-R's latent imagination: the latent state, the latent world model and the task-completion scorer.

- :class:`LatentEncoder` maps the current observation to ``s_t = [z_q, z_o]`` (robot state and
  point cloud); it starts as a copy of the trained policy's encoders and is fine-tuned on the
  mixed data, while the policy itself stays frozen.
- :class:`LatentWorldModel` imagines the latent after an action chunk:
  ``s_hat_{t+k} = s_t + W(s_t, a_{t:t+k})``, with a Transformer encoder over the latent token and
  one token per action.
- :class:`TaskCompletionScorer` gives the logit of eventual task completion from a latent.
- :class:`ScorerEnsemble` stacks several scorers, trained on imagined latents, whose
  disagreement tells how far a candidate's score can be trusted.

Each takes and returns tensors (what :class:`~torchrl_dalir.reranking.RerankingActor` calls at
every decision). :class:`LatentEncoderModule`, :class:`WorldModelModule`, :class:`ScorerModule`
and :class:`ScorerEnsembleModule` are the same modules (shared, not copied) as TensorDict modules
with declared ``in_keys``/``out_keys`` (defaults from :mod:`torchrl_dalir.keys`), to compose in a
``TensorDictSequential``: encoder -> world model -> scorer.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import EnsembleModule, TensorDictModule
from torch import nn

from torchrl_dalir import keys
from torchrl_dalir.modules.encoders import PointCloudEncoder, StateEncoder
from torchrl_dalir.modules.normalizer import MinMaxNormalizer
from torchrl_dalir.utils import require_keys

# What LatentEncoder.from_policy copies: DP3's observation encoders and their normalizers (ChunkPolicy3D's).
POLICY_ENCODERS = ("point_normalizer", "point_encoder", "state_normalizer", "state_encoder")


class LatentEncoder(nn.Module):
    """``s_t = [state features, point-cloud features]`` of one observation (no history).

    It starts as a copy of the policy's encoders (:meth:`from_policy`) when the policy has DP3's
    (:class:`~torchrl_dalir.modules.ChunkPolicy3D`); for a policy of another design
    (:class:`~torchrl_dalir.modules.ChunkPolicy`), :meth:`fresh` builds one of DP3's architecture
    to be trained with the scorer (``train_world_model`` does either). Its normalizers then need
    fitting (:meth:`fit_normalizers`).

    Args:
        point_normalizer, point_encoder, state_normalizer, state_encoder: modules with the
            interfaces of :class:`~torchrl_dalir.modules.ChunkPolicy3D`'s; use :meth:`from_policy` or :meth:`fresh`.

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig, make_policy
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]),
        ...                      action_dim=4, state_dim=4)
        >>> encoder = LatentEncoder.from_policy(policy)  # a trainable copy of the policy's encoders
        >>> encoder.latent_dim, encoder(torch.rand(5, 64, 3), torch.rand(5, 4)).shape
        (128, torch.Size([5, 128]))
        >>> LatentEncoder.fresh(**encoder.architecture()).latent_dim  # the same architecture, new weights
        128
    """

    def __init__(self, point_normalizer, point_encoder, state_normalizer, state_encoder):
        super().__init__()
        self.point_normalizer, self.point_encoder = point_normalizer, point_encoder
        self.state_normalizer, self.state_encoder = state_normalizer, state_encoder
        self.latent_dim = state_encoder.out_dim + point_encoder.out_dim

    @classmethod
    def from_policy(cls, policy) -> LatentEncoder:
        """A trainable copy of a policy's encoders and normalizers (the policy is not touched); the
        policy needs DP3's (:data:`POLICY_ENCODERS`), as :class:`~torchrl_dalir.modules.ChunkPolicy3D` has."""
        missing = [name for name in POLICY_ENCODERS if not hasattr(policy, name)]
        if missing:
            raise ValueError(
                f"{type(policy).__name__} has no {', '.join(missing)} to copy: build a new latent encoder with "
                "LatentEncoder.fresh(state_dim) and train it with the scorer "
                "(train_world_model(..., encoder=finetune) does)"
            )
        parts = [getattr(policy, name) for name in POLICY_ENCODERS]
        encoder = cls(*(copy.deepcopy(p) for p in parts))
        encoder.requires_grad_(True)
        return encoder

    @classmethod
    def fresh(
        cls,
        state_dim: int,
        point_hidden=(64, 128, 256),
        point_out: int = 64,
        state_hidden: int = 64,
        state_out: int = 64,
    ) -> LatentEncoder:
        """A new, trainable encoder of DP3's architecture (by default its sizes) for ``state_dim``-D robot
        states; its normalizers are the identity until fitted (:meth:`fit_normalizers`)."""
        return cls(
            MinMaxNormalizer(3),
            PointCloudEncoder(tuple(point_hidden), point_out),
            MinMaxNormalizer(state_dim),
            StateEncoder(state_dim, state_hidden, state_out),
        )

    def architecture(self) -> dict:
        """The sizes that :meth:`fresh` rebuilds this encoder's modules from (stored in world-model checkpoints)."""
        return {
            "state_dim": self.state_encoder.state_dim,
            "point_hidden": list(self.point_encoder.hidden),
            "point_out": self.point_encoder.out_dim,
            "state_hidden": self.state_encoder.hidden,
            "state_out": self.state_encoder.out_dim,
        }

    def fit_normalizers(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor) -> LatentEncoder:
        """Fits the point and state normalizers on observations (any leading shape)."""
        self.point_normalizer.fit(point_cloud)
        self.state_normalizer.fit(agent_pos)
        return self

    def point_features(self, point_cloud: torch.Tensor) -> torch.Tensor:
        return self.point_encoder.point_features(self.point_normalizer(point_cloud))

    def forward(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        if point_cloud.shape[-1] != 3 or point_cloud.shape[:-2] != agent_pos.shape[:-1]:
            raise ValueError(
                f"expected point_cloud [..., N, 3] and agent_pos [..., D] with the same batch, "
                f"got {tuple(point_cloud.shape)} and {tuple(agent_pos.shape)}"
            )
        z_o = self.point_encoder(self.point_normalizer(point_cloud))
        z_q = self.state_encoder(self.state_normalizer(agent_pos))
        return torch.cat([z_q, z_o], dim=-1)


class LatentWorldModel(nn.Module):
    """Predicts the latent residual of an action chunk with a Transformer encoder.

    Tokens: the latent ``s_t`` and the ``action_steps`` actions (normalised by the model's own
    min-max normalizer, fitted on the mixed data), each projected to ``hidden`` with a learned
    position embedding; the output at the latent token is the residual. The last layer starts at
    zero, so an untrained model predicts "no change".

    Args:
        latent_dim: size of ``s_t``.
        action_dim: size of an action.
        action_steps: chunk length ``k`` (the paper: 8).
        hidden, layers, heads: the Transformer (the paper: 256, 3, 4).
        action_input: ``False`` makes the action-ablated model of the paper's Table 4: the action
            tokens carry their position embeddings only, so the residual ignores the chunk (the same
            tokens and weights, the actions' information removed).

    Example:
        >>> wm = LatentWorldModel(latent_dim=128, action_dim=4, hidden=32, layers=1, heads=2)
        >>> wm.imagine(torch.randn(5, 128), torch.randn(5, 8, 4)).shape
        torch.Size([5, 128])
    """

    def __init__(
        self,
        latent_dim: int,
        action_dim: int,
        action_steps: int = 8,
        hidden: int = 256,
        layers: int = 3,
        heads: int = 4,
        action_input: bool = True,
    ):
        super().__init__()
        self.latent_dim, self.action_dim, self.action_steps = latent_dim, action_dim, action_steps
        self.action_input = action_input
        self.action_normalizer = MinMaxNormalizer(action_dim)
        self.latent_in = nn.Linear(latent_dim, hidden)
        self.action_in = nn.Linear(action_dim, hidden)
        self.position = nn.Parameter(torch.zeros(1 + action_steps, hidden))
        nn.init.normal_(self.position, std=0.02)
        layer = nn.TransformerEncoderLayer(hidden, heads, 4 * hidden, dropout=0.0, batch_first=True, norm_first=True)
        self.transformer = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.out = nn.Sequential(nn.LayerNorm(hidden), nn.Linear(hidden, latent_dim))
        nn.init.zeros_(self.out[-1].weight)
        nn.init.zeros_(self.out[-1].bias)

    def forward(self, latent: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The residual ``W(s_t, a)`` for latents ``[..., L]`` and chunks ``[..., k, A]``."""
        if actions.shape[-2:] != (self.action_steps, self.action_dim):
            raise ValueError(
                f"action chunks must be [..., {self.action_steps}, {self.action_dim}], got {tuple(actions.shape)}"
            )
        batch = latent.shape[:-1]
        action_tokens = self.action_in(self.action_normalizer(actions))
        if not self.action_input:
            action_tokens = torch.zeros_like(action_tokens)
        tokens = torch.cat([self.latent_in(latent).unsqueeze(-2), action_tokens], dim=-2) + self.position
        hidden = self.transformer(tokens.reshape(-1, *tokens.shape[-2:]))
        return self.out(hidden[:, 0]).reshape(*batch, self.latent_dim)

    def imagine(self, latent: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``s_hat_{t+k} = s_t + W(s_t, a_{t:t+k})``."""
        return latent + self(latent, actions)


class TaskCompletionScorer(nn.Module):
    """Logit of eventual task completion from a latent: an MLP ``L -> hidden -> hidden -> 1``.

    Example:
        >>> TaskCompletionScorer(128)(torch.randn(5, 128)).shape
        torch.Size([5])
    """

    def __init__(self, latent_dim: int, hidden: int = 256):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(latent_dim, hidden), nn.Mish(), nn.Linear(hidden, hidden), nn.Mish(), nn.Linear(hidden, 1)
        )

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        return self.net(latent).squeeze(-1)


class _EnsembleModule(EnsembleModule):
    """tensordict's ``EnsembleModule``, made picklable and deep-copyable: it keeps a vmapped
    function bound to itself, which a copy would otherwise share with the original."""

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("vmapped_forward", None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self.vmapped_forward = torch.vmap(self._func_module_call, 0)  # as built with expand_input=False


class ScorerEnsemble(nn.Module):
    """``members`` task-completion scorers with independent initialisations, evaluated in one
    vectorised call (tensordict's :class:`~tensordict.nn.EnsembleModule`). During training each
    member draws its own random batches (deep-ensemble style; no bootstrap resampling).

    DALI-R trains it on *imagined* latents of recorded chunks, ``s_hat_{t+k} = s_t + W(s_t,
    a_{t:t+k})``, against the completion target at ``t + k``: a value of the state and the chunk
    whose training inputs match what it scores at inference, and whose members' disagreement
    measures how far a candidate's score can be trusted.

    Example:
        >>> ensemble = ScorerEnsemble(128, hidden=32, members=5)
        >>> ensemble(torch.randn(7, 128)).shape       # every member scores every latent
        torch.Size([5, 7])
        >>> ensemble(torch.randn(5, 7, 128), per_member=True).shape   # one batch per member
        torch.Size([5, 7])
    """

    LATENT_KEY, LOGIT_KEY = keys.LATENT, keys.COMPLETION_LOGIT  # the members' TensorDict keys

    def __init__(self, latent_dim: int, hidden: int = 256, members: int = 5):
        super().__init__()
        if members < 1:
            raise ValueError(f"an ensemble needs at least one member, got {members}")
        member = TensorDictModule(
            TaskCompletionScorer(latent_dim, hidden), in_keys=[self.LATENT_KEY], out_keys=[self.LOGIT_KEY]
        )
        self.ensemble = _EnsembleModule(member, members, expand_input=False)
        self.ensemble.module.requires_grad_(False)  # the template: only the stacked copies are used
        self.latent_dim, self.members = latent_dim, members

    def forward(self, latent: torch.Tensor, per_member: bool = False) -> torch.Tensor:
        """Logits ``[E, ...]``: of every member on latents ``[..., L]``, or (``per_member``) of
        member ``e`` on ``latent[e]`` for latents ``[E, ..., L]``."""
        if latent.shape[-1] != self.latent_dim or (per_member and latent.shape[0] != self.members):
            raise ValueError(
                f"expected latents [{self.members if per_member else '...'}, ..., {self.latent_dim}], "
                f"got {tuple(latent.shape)}"
            )
        if not per_member:
            latent = latent.expand(self.members, *latent.shape)
        inputs = TensorDict({self.LATENT_KEY: latent}, batch_size=latent.shape[:-1])
        return self.ensemble(inputs).get(self.LOGIT_KEY)

    def member_logits(self, latent: torch.Tensor) -> torch.Tensor:
        """Logits ``[..., E]`` of every member on latents ``[..., L]``: the members last, so that
        the batch dimensions lead (as a tensordict's batch size needs)."""
        return self(latent).movedim(0, -1)


class _TensorModule(TensorDictModule):
    """A tensor-level module as a ``TensorDictModule`` that reads ``in_keys`` and writes ``out_keys``
    (by default the subclass's ``DEFAULT_IN_KEYS``/``DEFAULT_OUT_KEYS``), calling ``METHOD``."""

    DEFAULT_IN_KEYS: tuple[NestedKey, ...] = ()
    DEFAULT_OUT_KEYS: tuple[NestedKey, ...] = ()
    METHOD: str | None = None  # None: the module's forward

    def __init__(
        self,
        module: nn.Module,
        *,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
    ):
        in_keys = list(in_keys if in_keys is not None else self.DEFAULT_IN_KEYS)
        out_keys = list(out_keys if out_keys is not None else self.DEFAULT_OUT_KEYS)
        for name, given, expected in (
            ("in_keys", in_keys, self.DEFAULT_IN_KEYS),
            ("out_keys", out_keys, self.DEFAULT_OUT_KEYS),
        ):
            if len(given) != len(expected):
                raise ValueError(
                    f"{type(self).__name__} takes {len(expected)} {name} (like the default {list(expected)}), "
                    f"got {given}"
                )
        super().__init__(module, in_keys=in_keys, out_keys=out_keys, method=self.METHOD)

    def forward(self, tensordict: TensorDictBase, *args, **kwargs) -> TensorDictBase:
        require_keys(tensordict, self.in_keys, type(self).__name__)
        return super().forward(tensordict, *args, **kwargs)


class LatentEncoderModule(_TensorModule):
    """:class:`LatentEncoder` as a TensorDict module: the latent ``s_t`` of the current observation.

    Args:
        encoder: the latent encoder (shared, not copied).
        in_keys: the point cloud ``[..., N, 3]`` and the robot state ``[..., D]`` of one observation, no
            history (default ``point_cloud``, ``agent_pos``).
        out_keys: the latent ``[..., L]`` (default ``latent``).

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig, make_policy
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]),
        ...                      action_dim=4, state_dim=4)
        >>> module = LatentEncoderModule(LatentEncoder.from_policy(policy))
        >>> td = TensorDict({"point_cloud": torch.rand(5, 64, 3), "agent_pos": torch.rand(5, 4)}, [5])
        >>> module(td)["latent"].shape
        torch.Size([5, 128])
    """

    DEFAULT_IN_KEYS = (keys.POINT_CLOUD, keys.AGENT_POS)
    DEFAULT_OUT_KEYS = (keys.LATENT,)


class WorldModelModule(_TensorModule):
    """:class:`LatentWorldModel` as a TensorDict module: the imagined latent after an action chunk,
    ``s_hat_{t+k} = s_t + W(s_t, a_{t:t+k})`` (:meth:`LatentWorldModel.imagine`).

    Args:
        world_model: the latent world model (shared, not copied).
        in_keys: the latent ``[..., L]`` and the ``k`` actions to execute ``[..., k, A]`` (default
            ``latent``, ``action_chunk``, as in the training windows; a policy's 16-action chunk
            executes its ``policy.config.executed`` slice).
        out_keys: the imagined latent ``[..., L]`` (default ``imagined_latent``).

    Example:
        >>> module = WorldModelModule(LatentWorldModel(latent_dim=128, action_dim=4, hidden=32, layers=1, heads=2))
        >>> td = TensorDict({"latent": torch.randn(5, 128), "action_chunk": torch.randn(5, 8, 4)}, [5])
        >>> module(td)["imagined_latent"].shape
        torch.Size([5, 128])
    """

    DEFAULT_IN_KEYS = (keys.LATENT, keys.ACTION_CHUNK)
    DEFAULT_OUT_KEYS = (keys.IMAGINED_LATENT,)
    METHOD = "imagine"


class ScorerModule(_TensorModule):
    """:class:`TaskCompletionScorer` as a TensorDict module: the completion logit of a latent.

    Args:
        scorer: the task-completion scorer (shared, not copied).
        in_keys: the latent to score ``[..., L]`` (default ``imagined_latent``, what DALI-R scores;
            ``["latent"]`` scores the current state).
        out_keys: the logit ``[...]`` (default ``completion_logit``).

    Example:
        >>> module = ScorerModule(TaskCompletionScorer(128, hidden=32))
        >>> module(TensorDict({"imagined_latent": torch.randn(5, 128)}, [5]))["completion_logit"].shape
        torch.Size([5])
    """

    DEFAULT_IN_KEYS = (keys.IMAGINED_LATENT,)
    DEFAULT_OUT_KEYS = (keys.COMPLETION_LOGIT,)


class ScorerEnsembleModule(_TensorModule):
    """:class:`ScorerEnsemble` as a TensorDict module: every member's completion logit of a latent
    (:meth:`ScorerEnsemble.member_logits`).

    Args:
        ensemble: the scorer ensemble (shared, not copied).
        in_keys: the latent to score ``[..., L]`` (default ``imagined_latent``).
        out_keys: the members' logits ``[..., E]`` (default ``member_logits``).

    Example:
        >>> module = ScorerEnsembleModule(ScorerEnsemble(128, hidden=32, members=3))
        >>> module(TensorDict({"imagined_latent": torch.randn(5, 128)}, [5]))["member_logits"].shape
        torch.Size([5, 3])
    """

    DEFAULT_IN_KEYS = (keys.IMAGINED_LATENT,)
    DEFAULT_OUT_KEYS = (keys.MEMBER_LOGITS,)
    METHOD = "member_logits"
