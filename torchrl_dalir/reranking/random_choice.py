"""A control for DALI-R's ablations: the same candidates, chosen without the scorer."""

from __future__ import annotations

import dataclasses

import torch

from torchrl_dalir.reranking.actor import RerankingActor


class RandomCandidateActor(RerankingActor):
    """Builds and samples candidates exactly like :class:`RerankingActor`, then executes one
    chosen uniformly at random. Against DALI-R on the same episodes it separates what the
    scorer's choice adds from what the perturbed candidates do on their own.

    Its ``candidate_scores`` are the random draws that made the choice, not completion
    probabilities.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_dalir.modules import (LatentEncoder, LatentWorldModel, PolicyConfig, TaskCompletionScorer,
        ...                                    make_policy)
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]), 4, 4)
        >>> parts = (LatentEncoder.from_policy(policy), LatentWorldModel(128, 4, hidden=32, layers=1, heads=2),
        ...          TaskCompletionScorer(128))
        >>> control = RandomCandidateActor(policy, *parts, num_candidates=4, seed=1)
        >>> td = control(TensorDict(point_cloud=torch.rand(3, 2, 64, 3), agent_pos=torch.rand(3, 2, 4), batch_size=[3]))
        >>> torch.equal(td["dalir", "chosen_candidate"], td["dalir", "candidate_scores"].argmax(-1))  # the largest draw
        True
    """

    uses_selection = False  # always the arg-max of the random draws

    def __init__(self, *args, **kwargs):
        kwargs.pop("selection", None)
        if kwargs.get("config") is not None:
            kwargs["config"] = dataclasses.replace(kwargs["config"], selection=None)
        super().__init__(*args, **kwargs)

    @torch.no_grad()
    def member_scores(self, cloud: torch.Tensor, agent_pos: torch.Tensor, chunks: torch.Tensor) -> torch.Tensor:
        return torch.rand(chunks.shape[:2], generator=self.generator).to(chunks.device).unsqueeze(1)
