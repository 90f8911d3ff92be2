"""Selection rules: which of the scored candidates DALI-R executes.

The paper takes the arg-max of the scores. With a learned scorer whose differences between the
candidates of one decision are smaller than its own error, the arg-max chooses on noise and
over-optimises the proxy (Gao et al. 2022), so the rule is a setting of its own:

- ``argmax``: the highest mean score (the paper's rule);
- ``pessimistic``: the highest ``mean - k * std`` over the scorer ensemble's members (SAILOR);
- ``softmax``: a candidate drawn with probability ``softmax(mean / temperature)`` (V-GPS);
- ``margin``: stay with the clean candidate (the base policy's own chunk) unless another one's
  pessimistic *advantage* over it, ``mean - k * std`` of ``score_j - score_0`` over the members,
  exceeds ``margin``. ``margin=inf`` is the base policy; ``k=0, margin=0`` the arg-max.
- ``trust``: the arg-max among the ``fraction`` of candidates whose executed actions lie nearest
  the candidates' mean (a trust region: the world model has seen chunks like the policy's typical
  ones, and the highest scores tend to go to the outliers). ``fraction=1`` is the arg-max; a
  fraction that leaves one candidate picks the medoid, the scores unused.

Scores are completion probabilities ``[B, E, K]``: ``E`` ensemble members (1 for a single
scorer, whose std is then 0) by ``K`` candidates, candidate 0 the clean one.
"""

from __future__ import annotations

import torch

from torchrl_dalir.selection_config import RULES, SCORERS, SelectionConfig

__all__ = ["RULES", "SCORERS", "SelectionConfig", "select"]


def select(
    scores: torch.Tensor,
    config: SelectionConfig,
    generator: torch.Generator | None = None,
    actions: torch.Tensor | None = None,
) -> torch.Tensor:
    """The index ``[B]`` of the candidate to execute, from member scores ``[B, E, K]`` (and, for
    ``trust``, the candidates' executed actions ``[B, K, k, A]``).

    Example:
        >>> scores = torch.tensor([[[0.1, 0.9, 0.5]]])
        >>> actions = torch.tensor([[[[0.0]], [[3.0]], [[0.5]]]])  # the mean is 7/6: candidate 1 lies furthest
        >>> (select(scores, SelectionConfig("argmax")).item(),
        ...  select(scores, SelectionConfig("trust", fraction=0.67), actions=actions).item())
        (1, 2)
    """
    if scores.dim() != 3:
        raise ValueError(f"scores must be [batch, members, candidates], got {tuple(scores.shape)}")
    mean, std = scores.mean(1), scores.std(1, correction=0)
    if config.rule == "argmax":
        return mean.argmax(-1)
    if config.rule == "trust":
        if actions is None or actions.shape[:2] != (scores.shape[0], scores.shape[-1]):  # [B, K]
            raise ValueError(
                "the trust rule needs the candidates' actions [batch, candidates, ...] "
                f"for scores of shape {tuple(scores.shape)}"
            )
        distance = (actions - actions.mean(1, keepdim=True)).flatten(2).norm(dim=-1)  # [B, K] from the candidates' mean
        kept = max(1, round(config.fraction * scores.shape[-1]))
        nearest = distance.topk(kept, dim=-1, largest=False).indices
        return nearest.gather(-1, mean.gather(-1, nearest).argmax(-1, keepdim=True)).squeeze(-1)
    if config.rule == "pessimistic":
        return (mean - config.k * std).argmax(-1)
    if config.rule == "softmax":
        probabilities = torch.softmax(mean.double() / config.temperature, -1)
        return torch.multinomial(probabilities.cpu(), 1, generator=generator).squeeze(-1).to(scores.device)
    advantage = scores - scores[..., :1]  # over the clean candidate, per member
    lower = advantage.mean(1) - config.k * advantage.std(1, correction=0)
    best = lower.argmax(-1)
    leave = lower.gather(-1, best.unsqueeze(-1)).squeeze(-1) > config.margin
    return torch.where(leave, best, torch.zeros_like(best))
