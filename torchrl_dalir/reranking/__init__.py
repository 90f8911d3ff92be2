"""Inference-time reranking: candidate generators, action-space search and the ``RerankingActor``."""

from torchrl_dalir.reranking.actor import CANDIDATE_SCORES, CHOSEN_CANDIDATE, RerankingActor
from torchrl_dalir.reranking.candidates import CleanObservation, GaussianObservationNoise, PointDropout
from torchrl_dalir.reranking.random_choice import RandomCandidateActor
from torchrl_dalir.reranking.search import SEARCH_METHODS, SearchConfig

__all__ = [
    "CANDIDATE_SCORES", "CHOSEN_CANDIDATE", "CleanObservation", "GaussianObservationNoise", "PointDropout", "RandomCandidateActor",
    "RerankingActor", "SEARCH_METHODS", "SearchConfig",
]
