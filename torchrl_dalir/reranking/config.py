"""DALI-R's reranking settings in one record, :class:`RerankingConfig`: every default written once.

The actor (:class:`~torchrl_dalir.reranking.RerankingActor`), the evaluation functions
(:func:`~torchrl_dalir.evaluation.compare.evaluate_checkpoints`, the calibration), the main job's
configuration and the example scripts take their defaults from it. The jobs keep their
command-line names (``num_candidates=``, ``dropout=``) as fields whose defaults are this record's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

from torchrl_dalir.config import check_at_least, check_choice, check_probability
from torchrl_dalir.reranking.search import SearchConfig
from torchrl_dalir.selection_config import SelectionConfig

#: The candidate generators by name (torchrl_dalir.reranking.candidates): point dropout (DALI-R's),
#: Gaussian observation noise (the paper's baseline), the clean observation only (an action-space search's seeds).
CANDIDATE_GENERATORS = ("dropout", "noise", "clean")


@dataclass
class RerankingConfig:
    """How DALI-R makes, scores and chooses its candidates (the paper's settings by default).

    Args:
        num_candidates: candidates per decision, the clean one included (the paper: 32).
        candidates: the candidate generator, one of :data:`CANDIDATE_GENERATORS`: ``dropout``
            (:class:`~torchrl_dalir.reranking.PointDropout`, the paper's), ``noise``
            (:class:`~torchrl_dalir.reranking.GaussianObservationNoise`) or ``clean``
            (:class:`~torchrl_dalir.reranking.CleanObservation`).
        dropout: point dropout's probability of dropping a point (the paper: 0.2).
        noise_std: the observation noise's standard deviation, in metres.
        selection: the selection rule; ``None``: the rule stored in the world-model checkpoint when
            the actor is built from one (:meth:`~torchrl_dalir.reranking.RerankingActor.on_policy`),
            else the paper's arg-max.
        search: an action-space search around the candidates (default: none).
        common_noise: the clean candidate is sampled as the base policy samples (its own call and
            noise stream), see :class:`~torchrl_dalir.reranking.RerankingActor`; the evaluation
            functions turn it on.
        decisions: rerank only an episode's first ``decisions`` decisions and let the base policy act
            alone after them (0: rerank every decision). Branched outcomes show where a choice matters:
            on MetaWorld, 21 of the 22 episodes an oracle fixed were fixed at the first decision. The
            actor counts decisions from TorchRL's ``StepCounter`` (``step_count``) or, for
            ``decisions=1``, from the ``InitTracker``'s ``is_init``.

    Example:
        >>> config = RerankingConfig(num_candidates=8)
        >>> config.candidates, config.dropout, config.selection, config.search.method
        ('dropout', 0.2, None, 'none')
        >>> config.updated(dropout=0.3, selection=None).dropout  # None leaves a setting as it is
        0.3
    """

    num_candidates: int = 32
    candidates: str = "dropout"
    dropout: float = 0.2
    noise_std: float = 0.01
    selection: SelectionConfig | None = None
    search: SearchConfig = field(default_factory=SearchConfig)
    common_noise: bool = False
    decisions: int = 0

    def __post_init__(self):
        check_at_least("num_candidates", self.num_candidates, 1)
        check_at_least("decisions", self.decisions, 0)
        check_choice("candidates", self.candidates, CANDIDATE_GENERATORS)
        check_probability("dropout", self.dropout)
        if not self.noise_std >= 0 or math.isinf(self.noise_std):
            raise ValueError(f"noise_std must be a non-negative number of metres, got {self.noise_std}")
        if self.search.method != "none" and self.num_candidates < 2:
            raise ValueError(
                f"search {self.search.method} keeps candidate 0 clean and needs num_candidates >= 2, "
                f"got {self.num_candidates}"
            )

    @property
    def generator_setting(self) -> float:
        """The candidate generator's own setting (the dropout probability, the noise std, or 0 for ``clean``)."""
        return {"dropout": self.dropout, "noise": self.noise_std}.get(self.candidates, 0.0)

    @classmethod
    def with_generator(cls, candidates: str, setting: float, **settings) -> RerankingConfig:
        """The config whose generator ``candidates`` has ``setting`` (the inverse of :attr:`generator_setting`),
        e.g. the one a branched dataset's meta records."""
        own = {"dropout": {"dropout": setting}, "noise": {"noise_std": setting}}.get(candidates, {})
        return cls(candidates=candidates, **own, **settings)

    def updated(self, **settings) -> RerankingConfig:
        """A copy with ``settings`` replaced, those given as ``None`` left as they are (keyword
        arguments that default to ``None`` override the record only when given)."""
        unknown = set(settings) - {f.name for f in fields(self)}
        if unknown:
            raise TypeError(
                f"RerankingConfig has no {sorted(unknown)}; its settings are {[f.name for f in fields(self)]}"
            )
        return replace(self, **{name: value for name, value in settings.items() if value is not None})
