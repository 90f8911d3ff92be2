"""Common random numbers: DALI-R keeping its clean candidate replays the base policy."""

from torchrl_dalir.evaluation.compare import evaluate_checkpoints
from torchrl_dalir.reranking.selection import SelectionConfig


def test_keeping_the_clean_candidate_with_common_noise_replays_the_base_policy(trained_world_model):
    _, wm_path, policy_path = trained_world_model
    clean = SelectionConfig("margin", margin=1.0)  # never leaves the clean candidate
    kwargs = dict(episodes=2, seed=1, num_candidates=4, progress=False, selection=clean, methods=["base", "dalir"])
    shared = evaluate_checkpoints(policy_path, wm_path, **kwargs)  # common noise is the default
    base = [(r["steps"], r["episode_return"]) for r in shared["base policy"]["records"]]
    # ... so DALI-R's row is the base policy's, not run again; run on its own, it plays the same episodes
    assert (
        shared["DALI-R"]["replays"] == "base policy" and shared["DALI-R"]["records"] == shared["base policy"]["records"]
    )
    alone = evaluate_checkpoints(policy_path, wm_path, **{**kwargs, "methods": ["dalir"]})["DALI-R"]
    assert "replays" not in alone and all(r["details"]["clean_chosen"] == 1.0 for r in alone["records"])
    assert [(r["steps"], r["episode_return"]) for r in alone["records"]] == base
    own = evaluate_checkpoints(policy_path, wm_path, common_noise=False, **kwargs)["DALI-R"]["records"]
    assert [(r["steps"], r["episode_return"]) for r in own] != base  # its own noise: other trajectories
