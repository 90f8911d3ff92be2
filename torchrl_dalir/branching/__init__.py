"""Instruments that branch the simulator: beside the method, never inside a deployed actor.

Each runs every candidate of a decision from one saved simulator state, then the base policy to the episode's
end, on validation episodes or data seeds, never at a test decision:

- :mod:`~torchrl_dalir.branching.simulator`: saving and restoring a state, a decision's candidates, one branch
  (common random numbers: candidate 0's branch is the base episode itself);
- :mod:`~torchrl_dalir.branching.ceiling`: the clairvoyant oracle's ceiling over a decision's candidates;
- :mod:`~torchrl_dalir.branching.candidate_outcomes`: imagined against real outcomes of the candidates;
- :mod:`~torchrl_dalir.branching.outcomes`: branched outcomes as training rows for a critic
  (``BranchedOutcomes``, ``collect_branched``);
- :mod:`~torchrl_dalir.branching.outcome_noise`: outcomes under further noise draws, the honest ceiling and the
  simulator's privileged state replayed at a decision (for the teacher);
- :mod:`~torchrl_dalir.branching.scorer_benchmark`: the committed decisions and every scorer's ladder on them.

What they train (the chunk critic, the distilled student) is deployed through
:class:`~torchrl_dalir.reranking.RerankingActor`; the instruments are not.
"""
