"""Common random numbers: DALI-R keeping its clean candidate replays the base policy."""

from torchrl_dalir.evaluation.compare import evaluate_checkpoints
from torchrl_dalir.reranking.selection import SelectionConfig


def test_keeping_the_clean_candidate_with_common_noise_replays_the_base_policy(trained_world_model):
    _, wm_path, policy_path = trained_world_model
    clean = SelectionConfig("margin", margin=1.0)  # never leaves the clean candidate
    kwargs = dict(episodes=2, seed=1, num_candidates=4, progress=False, selection=clean, methods=["base", "dalir"])
    shared = evaluate_checkpoints(policy_path, wm_path, **kwargs)  # common noise is the default
    base = [(r["steps"], r["episode_return"]) for r in shared["base policy"]["records"]]
    assert [(r["steps"], r["episode_return"]) for r in shared["DALI-R"]["records"]] == base
    own = evaluate_checkpoints(policy_path, wm_path, common_noise=False, **kwargs)["DALI-R"]["records"]
    assert [(r["steps"], r["episode_return"]) for r in own] != base  # its own noise: other trajectories

