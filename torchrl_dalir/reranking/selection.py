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

import math
from dataclasses import asdict, dataclass

import torch

from torchrl_dalir.config import check_choice

RULES = ("argmax", "pessimistic", "softmax", "margin", "trust")
SCORERS = ("state", "ensemble")


@dataclass
class SelectionConfig:
    """A selection rule and its settings (stored in the world-model checkpoint once calibrated).

    Args:
        rule: one of :data:`RULES`.
        scorer: ``state`` (the paper's scorer, trained on encoded real observations, applied to
            the imagined latent) or ``ensemble`` (the scorer ensemble trained on imagined latents
            of recorded chunks, see :class:`~torchrl_dalir.modules.ScorerEnsemble`).
        k: pessimism, in ensemble standard deviations (``pessimistic``, ``margin``).
        temperature: the softmax temperature, in probability units (``softmax``).
        margin: the advantage over the clean candidate needed to leave it (``margin``).
        fraction: the share of candidates, nearest the candidates' mean, that ``trust`` chooses among.
    """

    rule: str = "argmax"
    scorer: str = "state"
    k: float = 0.0
    temperature: float = 0.01
    margin: float = 0.0
    fraction: float = 1.0

    def __post_init__(self):
        check_choice("selection rule", self.rule, RULES)
        check_choice("selection scorer", self.scorer, SCORERS)
        if self.k < 0 or self.temperature <= 0 or math.isnan(self.margin) or not 0 < self.fraction <= 1:
            raise ValueError(f"need k >= 0, temperature > 0, a margin that is a number and a fraction in (0, 1]; got {self}")

    @property
    def name(self) -> str:
        """A short, unique description, e.g. ``margin(ensemble, k=1, margin=0.02)``."""
        settings = {"pessimistic": f", k={self.k:g}", "softmax": f", T={self.temperature:g}",
                    "margin": f", k={self.k:g}, margin={self.margin:g}", "trust": f", fraction={self.fraction:g}"}.get(self.rule, "")
        return f"{self.rule}({self.scorer}{settings})"

    @property
    def keeps_clean(self) -> bool:
        """Whether the rule executes the clean candidate at every decision whatever the scores:
        ``margin`` with a margin of at least 1, which no advantage between probabilities exceeds.
        With common noise such a DALI-R is the base policy, episode for episode."""
        return self.rule == "margin" and self.margin >= 1

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def stored_in(cls, checkpoint: dict) -> SelectionConfig:
        """The rule a loaded world-model checkpoint names (the paper's arg-max if it names none)."""
        return cls(**checkpoint.get("selection", {}))


def select(scores: torch.Tensor, config: SelectionConfig, generator: torch.Generator | None = None,
           actions: torch.Tensor | None = None) -> torch.Tensor:
    """The index ``[B]`` of the candidate to execute, from member scores ``[B, E, K]`` (and, for
    ``trust``, the candidates' executed actions ``[B, K, k, A]``).

    Example:
        >>> scores = torch.tensor([[[0.1, 0.9, 0.5]]])
        >>> actions = torch.tensor([[[[0.0]], [[3.0]], [[0.5]]]])  # the mean is 7/6: candidate 1 lies furthest
        >>> select(scores, SelectionConfig("argmax")).item(), select(scores, SelectionConfig("trust", fraction=0.67), actions=actions).item()
        (1, 2)
    """
    if scores.dim() != 3:
        raise ValueError(f"scores must be [batch, members, candidates], got {tuple(scores.shape)}")
    mean, std = scores.mean(1), scores.std(1, correction=0)
    if config.rule == "argmax":
        return mean.argmax(-1)
    if config.rule == "trust":
        if actions is None or actions.shape[:2] != (scores.shape[0], scores.shape[-1]):  # [B, K]
            raise ValueError(f"the trust rule needs the candidates' actions [batch, candidates, ...] for scores of shape {tuple(scores.shape)}")
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
