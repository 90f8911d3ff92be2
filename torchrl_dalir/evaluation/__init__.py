"""Evaluation: success rates on seeded evaluation episodes."""

from torchrl_dalir.evaluation.success_rate import EpisodeRecord, EvaluationResult, evaluate

__all__ = ["EpisodeRecord", "EvaluationResult", "evaluate"]
