"""A control for DALI-R's ablations: the same candidates, chosen without the scorer."""

from __future__ import annotations

import torch

from torchrl_dalir.reranking.actor import RerankingActor


class RandomCandidateActor(RerankingActor):
    """Builds and samples candidates exactly like :class:`RerankingActor`, then executes one
    chosen uniformly at random. Against DALI-R on the same episodes it separates what the
    scorer's choice adds from what the perturbed candidates do on their own.

    Its ``candidate_scores`` are the random draws that made the choice, not completion
    probabilities.
    """

    def __init__(self, *args, **kwargs):
        kwargs.pop("selection", None)  # always the arg-max of the random draws
        super().__init__(*args, **kwargs)

    @torch.no_grad()
    def member_scores(self, cloud: torch.Tensor, agent_pos: torch.Tensor, chunks: torch.Tensor) -> torch.Tensor:
        return torch.rand(chunks.shape[:2], generator=self.generator).to(chunks.device).unsqueeze(1)
