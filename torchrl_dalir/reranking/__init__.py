"""Inference-time reranking: candidate generators, action-space search and the ``RerankingActor``."""

from torchrl_dalir.modules.policy_interface import ChunkPolicy
from torchrl_dalir.reranking.actor import CANDIDATE_SCORES, CHOSEN_CANDIDATE, RerankingActor
from torchrl_dalir.reranking.candidates import (
    CleanObservation,
    GaussianObservationNoise,
    PointDropout,
    candidate_generator,
)
from torchrl_dalir.reranking.config import CANDIDATE_GENERATORS, RerankingConfig
from torchrl_dalir.reranking.random_choice import RandomCandidateActor
from torchrl_dalir.reranking.search import SEARCH_METHODS, SearchConfig
from torchrl_dalir.reranking.selection import SelectionConfig

__all__ = [
    "CANDIDATE_GENERATORS",
    "CANDIDATE_SCORES",
    "CHOSEN_CANDIDATE",
    "ChunkPolicy",
    "CleanObservation",
    "GaussianObservationNoise",
    "PointDropout",
    "RandomCandidateActor",
    "RerankingActor",
    "RerankingConfig",
    "SEARCH_METHODS",
    "SearchConfig",
    "SelectionConfig",
    "candidate_generator",
]
