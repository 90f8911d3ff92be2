"""Inference-time reranking: candidate generators and the ``RerankingActor``."""

from torchrl_dalir.reranking.actor import CANDIDATE_SCORES, CHOSEN_CANDIDATE, RerankingActor
from torchrl_dalir.reranking.candidates import GaussianObservationNoise, PointDropout
from torchrl_dalir.reranking.random_choice import RandomCandidateActor

__all__ = ["CANDIDATE_SCORES", "CHOSEN_CANDIDATE", "GaussianObservationNoise", "PointDropout", "RandomCandidateActor", "RerankingActor"]
