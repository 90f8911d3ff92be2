"""``RerankingActor``: DALI-R's inference-time latent imagination and reranking (Algorithm 1)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from torchrl_dalir import keys
from torchrl_dalir.checkpoints.policy import load_policy
from torchrl_dalir.checkpoints.world_model import load_world_model
from torchrl_dalir.modules.chunk_critic import ChunkCritic
from torchrl_dalir.modules.policies import check_finite_output
from torchrl_dalir.modules.policy_interface import ChunkPolicy, check_chunk_policy, executed, read_observation
from torchrl_dalir.modules.world_model import LatentEncoder, LatentWorldModel, ScorerEnsemble, TaskCompletionScorer
from torchrl_dalir.reranking.candidates import candidate_generator
from torchrl_dalir.reranking.config import RerankingConfig
from torchrl_dalir.reranking.search import SearchConfig, search_candidates
from torchrl_dalir.reranking.selection import SelectionConfig, select

CANDIDATE_SCORES = ("dalir", "candidate_scores")  #: [..., K] sigmoid(C(s_hat)) of every candidate (ensemble mean)
CHOSEN_CANDIDATE = ("dalir", "chosen_candidate")  #: [...] index of the executed candidate (0 = clean)


def check_imagination(policy: ChunkPolicy, encoder: LatentEncoder, world_model: LatentWorldModel) -> None:
    """Refuses a world model that cannot imagine ``policy``'s executed actions from ``encoder``'s latents."""
    if world_model.action_dim != policy.action_dim:
        raise ValueError(
            f"the world model takes {world_model.action_dim}-D actions; the policy outputs {policy.action_dim}-D"
        )
    if world_model.action_steps != policy.action_steps:
        raise ValueError(
            f"the world model imagines {world_model.action_steps} actions; the policy executes {policy.action_steps}"
        )
    if world_model.latent_dim != encoder.latent_dim:
        raise ValueError("the world model and the latent encoder disagree on the latent size")


def check_critic(policy: ChunkPolicy, critic: ChunkCritic) -> None:
    """Refuses a chunk critic of other executed actions than ``policy``'s."""
    if (critic.action_dim, critic.action_steps) != (policy.action_dim, policy.action_steps):
        raise ValueError(
            f"the chunk critic scores {critic.action_steps} executed {critic.action_dim}-D actions; the policy "
            f"executes {policy.action_steps} {policy.action_dim}-D actions (train the critic on this policy's outcomes)"
        )


class RerankingActor(TensorDictModuleBase):
    """Samples candidate chunks from a frozen policy, imagines and scores each (or scores each with a chunk
    critic), executes one.

    At each decision: build ``num_candidates`` perturbed policy inputs (candidate 0 is always
    the clean observation), sample all chunks in one batched policy call, optionally search the
    action space around them (``search``), imagine each chunk's executed part with one
    world-model step from the current latent, score the imagined latents, choose by the
    ``selection`` rule (:mod:`~torchrl_dalir.reranking.selection`; the paper's is
    the arg-max) and write the chosen chunk to ``action_chunk`` (plus every score and the
    chosen index).
    Wrap it with :func:`~torchrl_dalir.receding_horizon` exactly like
    the base policy to execute 8 of 16 actions per decision; every step then carries its decision's
    scores and chosen index. :meth:`reset` replays its decisions from the start.

    Args:
        policy: the frozen base policy: any :class:`~torchrl_dalir.modules.ChunkPolicy` (checked here,
            naming what it lacks), e.g. this library's :class:`~torchrl_dalir.modules.ChunkPolicy3D`
            or a policy of your own (README, "Wrap your own policy").
        encoder, world_model, scorer: the latent imagination module (see
            :mod:`torchrl_dalir.modules.world_model`); leave all three out to rerank with a ``critic`` alone.
        config: the reranking settings (:class:`~torchrl_dalir.reranking.RerankingConfig`, by default
            the paper's: 32 point-dropout candidates with probability 0.2, the arg-max); the
            keyword arguments below, when given, replace its settings.
        num_candidates: candidates per decision (the paper: 32).
        candidates: the candidate generator (default: the one ``config`` names, :class:`PointDropout`
            ``(0.2)``; or :class:`~torchrl_dalir.reranking.candidates.GaussianObservationNoise`, or
            :class:`~torchrl_dalir.reranking.candidates.CleanObservation`, the seeds of an action-space search),
            or a generator's name (:data:`~torchrl_dalir.reranking.CANDIDATE_GENERATORS`).
        search: an action-space search around the generated candidates (default ``none``; random
            shooting, CEM, MPPI or score-gradient ascent on the selection's scorer, see
            :mod:`~torchrl_dalir.reranking.search`): the paper's Table 2 alternatives to point dropout.
            It works in the policy's normalised action space (its ``action_normalizer``), or in the
            world model's for a policy without one.
        seed: seeds candidate perturbations and policy noise, so decisions are reproducible.
        ensemble: the scorer ensemble trained on imagined latents (needed by
            ``selection.scorer="ensemble"``).
        critic: a :class:`~torchrl_dalir.modules.ChunkCritic` trained on branched outcomes (needed by
            ``selection.scorer="critic"``, which scores the chunks from the state, without imagination;
            the default selection when no world model is given), or a
            :class:`~torchrl_dalir.modules.PointCloudCritic`, which reads the cloud through encoders of its own.
        selection: the selection rule (default: the paper's arg-max of the state scorer).
            :meth:`from_checkpoints` uses the rule stored in the world-model checkpoint by
            ``examples/calibrate_selection.py`` unless one is passed.
        common_noise: candidate 0 is sampled exactly as the base policy samples (its own network
            call, its noise from the policy's own stream: torch's global generator unless the
            policy was seeded with its ``reset``) instead of with ``seed``'s noise in the
            candidates' batch (common random numbers): a rule that keeps the clean candidate then
            replays the base policy's episodes, so a paired comparison sees only the decisions
            where the rule switched (the evaluation functions' default). Costs one more batch-1
            policy call per decision; decisions then also depend on torch's global seed.
        in_keys: where it reads the point cloud and the robot state (default ``point_cloud``, ``agent_pos``).
        out_keys: where it writes the chosen chunk, the candidates' scores and the chosen index
            (default ``action_chunk``, :data:`CANDIDATE_SCORES`, :data:`CHOSEN_CANDIDATE`).

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_dalir.modules import (LatentEncoder, LatentWorldModel, PolicyConfig, TaskCompletionScorer,
        ...                                    make_policy)
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]),
        ...                      action_dim=4, state_dim=4)
        >>> encoder = LatentEncoder.from_policy(policy)  # untrained parts here; from_checkpoints loads trained ones
        >>> world_model = LatentWorldModel(encoder.latent_dim, action_dim=4, hidden=32, layers=1, heads=2)
        >>> scorer = TaskCompletionScorer(encoder.latent_dim, hidden=32)
        >>> dalir = RerankingActor(policy, encoder, world_model, scorer, num_candidates=4)
        >>> observation = TensorDict(point_cloud=torch.rand(2, 64, 3), agent_pos=torch.rand(2, 4))  # a 2-step history
        >>> decision = dalir(observation.clone())
        >>> decision["action_chunk"].shape, decision["dalir", "candidate_scores"].shape
        (torch.Size([16, 4]), torch.Size([4]))
        >>> dalir.reset()  # replays its decisions from the start
        >>> torch.equal(dalir(observation.clone())["action_chunk"], decision["action_chunk"])
        True
    """

    uses_selection = True  # chooses by its selection rule (a control that ignores the rule says False)

    def __init__(
        self,
        policy: ChunkPolicy,
        encoder: LatentEncoder | None = None,
        world_model: LatentWorldModel | None = None,
        scorer: TaskCompletionScorer | None = None,
        *,
        config: RerankingConfig | None = None,
        num_candidates: int | None = None,
        candidates=None,
        seed: int = 0,
        ensemble: ScorerEnsemble | None = None,
        critic: ChunkCritic | None = None,
        selection: SelectionConfig | None = None,
        search: SearchConfig | None = None,
        common_noise: bool | None = None,
        in_keys: Sequence[NestedKey] = (keys.POINT_CLOUD, keys.AGENT_POS),
        out_keys: Sequence[NestedKey] = (keys.ACTION_CHUNK, CANDIDATE_SCORES, CHOSEN_CANDIDATE),
    ):
        super().__init__()
        self.in_keys, self.out_keys = list(in_keys), list(out_keys)
        check_chunk_policy(policy, type(self).__name__)
        config = (config if config is not None else RerankingConfig()).updated(
            num_candidates=num_candidates,
            selection=selection,
            search=search,
            common_noise=common_noise,
            candidates=candidates if isinstance(candidates, str) else None,
        )
        imagination = (encoder, world_model, scorer)
        if all(part is None for part in imagination):
            if critic is None:
                raise ValueError(
                    f"{type(self).__name__} needs the latent encoder, world model and scorer "
                    "(RerankingActor.from_checkpoints), or a chunk critic (critic=load_chunk_critic(<critic.pt>))"
                )
            if config.selection is None:  # the critic is the only scorer there is
                config = config.updated(selection=SelectionConfig(scorer="critic"))
        elif any(part is None for part in imagination):
            raise ValueError("pass the latent encoder, the world model and the scorer together, or none of them")
        else:
            check_imagination(policy, encoder, world_model)
        self.config = config
        self.selection = config.selection if config.selection is not None else SelectionConfig()
        if self.selection.scorer != "critic" and world_model is None:
            raise ValueError(
                f"selection {self.selection.name} scores imagined latents: it needs the latent encoder, "
                "world model and scorer (only selection scorer='critic' works without them)"
            )
        if self.selection.scorer == "ensemble" and ensemble is None:
            raise ValueError(
                f"selection {self.selection.name} needs a scorer ensemble; this world model has none "
                "(checkpoints written before version 0.2.0 have none: retrain the world-model stage)"
            )
        if self.selection.scorer == "critic" and critic is None:
            raise ValueError(
                f"selection {self.selection.name} needs a chunk critic: pass critic=load_chunk_critic(<critic.pt>) "
                "(the main job's branched stage trains one)"
            )
        if critic is not None:
            check_critic(policy, critic)
        self.critic = critic.eval().requires_grad_(False) if critic is not None else None
        self.search = config.search
        self.search.check(config.num_candidates, policy.action_dim)
        self.policy, self.encoder, self.world_model, self.scorer, self.ensemble = (
            policy,
            encoder,
            world_model,
            scorer,
            ensemble,
        )
        for module in (policy, encoder, world_model, scorer, ensemble):
            if isinstance(module, nn.Module):
                module.eval().requires_grad_(False)
        self.executed = executed(policy)  # the chunk entries a decision executes, which the world model imagines
        self.num_candidates = config.num_candidates
        self.candidates = (
            candidates if candidates is not None and not isinstance(candidates, str) else candidate_generator(config)
        )
        self.seed, self.common_noise, self.decisions = seed, config.common_noise, config.decisions
        self.generator = torch.Generator().manual_seed(seed)

    def reset(self, seed: int | None = None) -> None:
        """Restarts candidates and choices from ``seed`` (by default the actor's own ``seed``), so the same object
        replays its decisions. With ``common_noise``, seed torch too (``torch.manual_seed``): the clean candidate
        draws from its global generator (unless the policy has its own, see ``ChunkPolicy3D.reset``)."""
        if seed is not None:
            self.seed = seed
        self.generator.manual_seed(self.seed)

    @classmethod
    def from_checkpoints(
        cls, policy_path: str | Path, world_model_path: str | Path, device="cpu", **kwargs
    ) -> RerankingActor:
        """Loads a policy and the world model trained on top of it; refuses a world model of
        another task or another policy (by the digest of the policy's weights that it records)."""
        return cls.on_policy(load_policy(policy_path, device), world_model_path, device, **kwargs)

    @classmethod
    def on_policy(cls, policy: ChunkPolicy, world_model_path: str | Path, device="cpu", **kwargs) -> RerankingActor:
        """Wraps an already loaded policy (any :class:`~torchrl_dalir.modules.ChunkPolicy`) with the
        world model trained on top of it; refuses a world model of another task or another policy
        (:func:`~torchrl_dalir.checkpoints.check_trained_on`). The selection rule is the
        checkpoint's unless ``selection=`` (or a ``config=`` with a ``selection``) is passed; a
        stored rule that always keeps the clean candidate (calibration found no rule that beat the
        base policy) is used with a warning, since the actor then executes the base policy's chunks
        at DALI-R's cost."""
        parts = load_world_model(world_model_path, device, policy=policy)
        given = "selection" in kwargs or (kwargs.get("config") is not None and kwargs["config"].selection is not None)
        if cls.uses_selection and not given and parts.selection.keeps_clean:
            warnings.warn(
                f"{world_model_path}: the calibrated rule {parts.selection.name} always keeps the clean candidate, "
                "so this actor executes the base policy's chunks; pass selection= to rerank anyway",
                stacklevel=2,
            )
        if not given:
            kwargs["selection"] = parts.selection
        return cls(policy, parts.encoder, parts.world_model, parts.scorer, ensemble=parts.ensemble, **kwargs)

    @torch.no_grad()
    def imagine(self, cloud: torch.Tensor, agent_pos: torch.Tensor, chunks: torch.Tensor) -> torch.Tensor:
        """Imagined latents ``[B, K, L]`` after the executed part of chunks ``[B, K, H, A]``,
        from observations ``[B, To, ...]``."""
        latent = self.encoder(cloud[:, -1], agent_pos[:, -1])  # s_t from the current observation
        return self._imagine_executed(latent, chunks[..., self.executed, :])

    def _imagine_executed(self, latent: torch.Tensor, executed: torch.Tensor) -> torch.Tensor:
        return self.world_model.imagine(latent.unsqueeze(1).expand(-1, executed.shape[1], -1), executed)

    def _probabilities(self, imagined: torch.Tensor) -> torch.Tensor:
        """Completion probabilities ``[B, E, K]`` of imagined latents ``[B, K, L]`` by each member of the
        selection's scorer."""
        if self.selection.scorer == "ensemble":
            return torch.sigmoid(self.ensemble(imagined)).transpose(0, 1)
        return torch.sigmoid(self.scorer(imagined)).unsqueeze(1)

    @torch.no_grad()
    def member_scores(self, cloud: torch.Tensor, agent_pos: torch.Tensor, chunks: torch.Tensor) -> torch.Tensor:
        """Completion probabilities ``[B, E, K]`` of chunks ``[B, K, H, A]`` by each of the ``E``
        members of the selection's scorer (``E = 1`` for the state scorer)."""
        if self.selection.scorer == "critic":  # Q of the chunk from the state: no imagination
            members = torch.sigmoid(
                self.critic(self.critic.condition(self.policy, cloud, agent_pos), chunks[..., self.executed, :])
            )
            members = members.unsqueeze(1)
        else:
            members = self._probabilities(self.imagine(cloud, agent_pos, chunks))
        scorer = "chunk critic" if self.selection.scorer == "critic" else "latent encoder, world model or scorer"
        check_finite_output(
            members,
            "DALI-R's candidate_scores",
            f"the {scorer} gave NaN (damaged weights, or an observation far outside the training data): "
            f"reload or retrain the {'critic' if self.selection.scorer == 'critic' else 'world model'}",
        )
        return members

    @torch.no_grad()
    def objective(self, cloud: torch.Tensor, agent_pos: torch.Tensor):
        """The score an action-space search maximises at observations ``[B, To, ...]``: a function
        from executed actions ``[B, N, k, A]`` (env units) to the members' mean completion
        probability ``[B, N]``, differentiable in the actions (the current latent is encoded once)."""
        if self.selection.scorer == "critic":
            cond = self.critic.condition(self.policy, cloud, agent_pos)
            return lambda executed: torch.sigmoid(self.critic(cond, executed))
        latent = self.encoder(cloud[:, -1], agent_pos[:, -1])
        return lambda executed: self._probabilities(self._imagine_executed(latent, executed)).mean(1)

    @torch.no_grad()
    def score(self, cloud: torch.Tensor, agent_pos: torch.Tensor, chunks: torch.Tensor) -> torch.Tensor:
        """Completion probabilities ``[B, K]`` (the members' mean) of chunks ``[B, K, H, A]``
        from observations ``[B, To, ...]``."""
        return self.member_scores(cloud, agent_pos, chunks).mean(1)

    @torch.no_grad()
    def sample_candidates(
        self, cloud: torch.Tensor, agent_pos: torch.Tensor, clean: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Candidate chunks ``[B, K, H, A]``; candidate 0 is the policy's sample from the clean
        observation, the others are perturbed-input samples, or what ``search`` found from them. With common
        noise, ``clean`` (``[B, H, A]``) is candidate 0 when the base policy's own call already drew it."""
        chunks = self._policy_samples(cloud, agent_pos, clean)
        if self.search.method == "none":
            return chunks
        objective = self.objective(cloud, agent_pos)
        return search_candidates(
            chunks, objective, self.search, self.search_normalizer(), self.executed, self.generator
        )

    def search_normalizer(self):
        """The action space an action-space search works in: the policy's normalised actions (its
        ``action_normalizer``), or, for a policy without one, the world model's (fitted on its data), or with no
        world model the critic's."""
        normalizer = getattr(self.policy, "action_normalizer", None)
        if normalizer is not None:
            return normalizer
        return (self.world_model if self.world_model is not None else self.critic).action_normalizer

    def _policy_samples(self, cloud: torch.Tensor, agent_pos: torch.Tensor, clean: torch.Tensor | None = None):
        cond = self.candidates.conditions(self.policy, cloud, agent_pos, self.num_candidates, self.generator)
        if not self.common_noise:
            return self.policy.sample(cond, self.generator)
        shape = (cond.shape[0], self.num_candidates, self.policy.horizon, self.policy.action_dim)
        noise = torch.randn(shape, generator=self.generator).to(cond.device)  # as without common noise
        if clean is None:
            clean = self.policy.sample(self.policy.encode(cloud, agent_pos))  # the base policy's own call, bit for bit
        return torch.cat([clean.unsqueeze(1), self.policy.sample(cond[:, 1:], noise=noise[:, 1:])], dim=1)

    @torch.no_grad()
    def propose(self, cloud: torch.Tensor, agent_pos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every candidate chunk ``[B, K, H, A]`` and its score ``[B, K]`` for observations
        ``[B, To, ...]``; candidate 0 comes from the clean observation."""
        chunks = self.sample_candidates(cloud, agent_pos)
        return chunks, self.score(cloud, agent_pos, chunks)

    def reranked(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Which entries of a decision's ``tensordict`` are reranked (flat ``[B]``): all of them, or with
        ``config.decisions`` those among their episode's first decisions, counted from ``step_count``
        (TorchRL's ``StepCounter``) or, for ``decisions=1``, from ``is_init`` (its ``InitTracker``)."""
        size = tensordict.numel()
        if not self.decisions:
            return torch.ones(size, dtype=torch.bool, device=tensordict.device)
        step_count = tensordict.get(keys.STEP_COUNT, default=None)
        if step_count is not None:
            return step_count.reshape(size) // self.policy.action_steps < self.decisions
        is_init = tensordict.get(keys.IS_INIT, default=None)
        if is_init is not None and self.decisions == 1:
            return is_init.reshape(size)
        raise KeyError(
            f"reranking only the first {self.decisions} decisions counts them from {keys.STEP_COUNT!r} "
            f"(add TorchRL's StepCounter to the env){' or is_init (an InitTracker)' if self.decisions == 1 else ''}"
        )

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        cloud, agent_pos = read_observation(self.policy, tensordict, self.in_keys)
        batch = cloud.shape[:-3]
        cloud, agent_pos = cloud.reshape(-1, *cloud.shape[-3:]), agent_pos.reshape(-1, *agent_pos.shape[-2:])
        rerank = self.reranked(tensordict).to(cloud.device)
        if rerank.all():
            chosen, scores, best = self._rerank(cloud, agent_pos)
        else:  # the others act as the base policy: its own sample, no scores, candidate 0
            keep, clean = ~rerank, None
            chosen = cloud.new_empty((len(cloud), self.policy.horizon, self.policy.action_dim))
            if self.common_noise:  # one call for every row, as the base policy samples; reranked rows keep theirs
                clean = self.policy.sample(self.policy.encode(cloud, agent_pos))
                chosen[keep] = clean[keep]
            else:
                chosen[keep] = self.policy.sample(self.policy.encode(cloud[keep], agent_pos[keep]), self.generator)
            scores = cloud.new_full((len(cloud), self.num_candidates), float("nan"))
            best = torch.zeros(len(cloud), dtype=torch.long, device=cloud.device)
            if rerank.any():
                clean = clean[rerank] if clean is not None else None
                chosen[rerank], scores[rerank], best[rerank] = self._rerank(cloud[rerank], agent_pos[rerank], clean)
        chunk_key, scores_key, chosen_key = self.out_keys
        tensordict.set(chunk_key, chosen.reshape(*batch, *chosen.shape[1:]))
        tensordict.set(scores_key, scores.reshape(*batch, -1))
        return tensordict.set(chosen_key, best.reshape(batch))

    def _rerank(self, cloud: torch.Tensor, agent_pos: torch.Tensor, clean: torch.Tensor | None = None):
        """The chosen chunks ``[B, H, A]``, every candidate's score ``[B, K]`` and the chosen indices ``[B]``."""
        chunks = self.sample_candidates(cloud, agent_pos, clean)
        members = self.member_scores(cloud, agent_pos, chunks)
        best = select(members, self.selection, self.generator, actions=chunks[..., self.executed, :])
        return chunks[torch.arange(len(best)), best], members.mean(1), best
