"""The settings of a selection rule: :class:`SelectionConfig`, what a world-model checkpoint stores
once calibrated and what :func:`~torchrl_dalir.reranking.selection.select` applies.

A plain record of settings, outside both :mod:`torchrl_dalir.checkpoints` (which stores it) and
:mod:`torchrl_dalir.reranking` (which applies it), so that neither package imports the other's
(``reranking`` reads checkpoints; ``checkpoints`` needs only this record). The rules themselves are
described in :mod:`torchrl_dalir.reranking.selection`, which re-exports it.

Example:
    >>> SelectionConfig("margin", "ensemble", k=1.0, margin=0.02).name
    'margin(ensemble, k=1, margin=0.02)'

"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from torchrl_dalir.config import check_choice

RULES = ("argmax", "pessimistic", "softmax", "margin", "trust")
SCORERS = ("state", "ensemble", "critic")


@dataclass
class SelectionConfig:
    """A selection rule and its settings (stored in the world-model checkpoint once calibrated).

    Args:
        rule: one of :data:`RULES`.
        scorer: ``state`` (the paper's scorer, trained on encoded real observations, applied to
            the imagined latent) or ``ensemble`` (the scorer ensemble trained on imagined latents
            of recorded chunks, see :class:`~torchrl_dalir.modules.ScorerEnsemble`) or ``critic``
            (a :class:`~torchrl_dalir.modules.ChunkCritic` of the state and the chunk, trained on branched
            outcomes; no world model involved).
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
            raise ValueError(
                f"need k >= 0, temperature > 0, a margin that is a number and a fraction in (0, 1]; got {self}"
            )

    @property
    def name(self) -> str:
        """A short, unique description, e.g. ``margin(ensemble, k=1, margin=0.02)``."""
        settings = {
            "pessimistic": f", k={self.k:g}",
            "softmax": f", T={self.temperature:g}",
            "margin": f", k={self.k:g}, margin={self.margin:g}",
            "trust": f", fraction={self.fraction:g}",
        }.get(self.rule, "")
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
