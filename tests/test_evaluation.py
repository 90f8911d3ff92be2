"""Evaluation episodes: the same episodes whatever the env renders."""

import torch

from torchrl_dalir import keys


def test_evaluation_renders_only_the_clouds_decisions_read_and_replays_the_same_episodes(trained_world_model):
    from torchrl_dalir import RerankingActor
    from torchrl_dalir.evaluation import evaluate
    from torchrl_dalir.modules.receding_horizon import receding_horizon
    from torchrl_dalir.reranking.actor import CANDIDATE_SCORES, CHOSEN_CANDIDATE

    _, wm_path, policy_path = trained_world_model
    actor = RerankingActor.from_checkpoints(policy_path, wm_path, num_candidates=3, seed=0)
    policy = actor.policy
    kwargs = dict(num_points=policy.num_points, history=policy.config.obs_steps, max_steps=20, progress=False)

    def records(decision_period=None):
        actor.reset(0)
        period = {} if decision_period is None else {"decision_period": decision_period}
        steps = []
        result = evaluate(
            receding_horizon(actor),
            "reach",
            2,
            seed=1,
            describe=lambda rollout: steps.append(rollout) or {},
            **period,
            **kwargs,
        )
        return result.to_dict()["episodes"], steps

    (lazy, lazy_rollouts), (every, every_rollouts) = records(), records(decision_period=1)
    assert lazy == every  # the same choices, actions and outcomes
    for a, b in zip(lazy_rollouts, every_rollouts):
        for key in (keys.ACTION, CHOSEN_CANDIDATE, CANDIDATE_SCORES):  # the same candidates, scores and choices
            assert torch.equal(a[key], b[key])
        rendered = torch.isfinite(a[keys.POINT_CLOUD]).reshape(a.shape[-1], -1).all(-1)  # [steps]: both frames rendered
        assert rendered.float().mean() < 0.5 and torch.isfinite(b[keys.POINT_CLOUD]).all()  # fewer renders here
        assert rendered.tolist() == [
            t % policy.config.action_steps == 0 for t in range(a.shape[-1])
        ]  # at the decisions only


def test_evaluation_runs_the_chosen_episodes_and_stops_when_told():
    from torchrl_dalir.evaluation import evaluate
    from torchrl_dalir.experts import make_expert
    from torchrl_dalir.seeds import eval_episode_seed

    expert = make_expert("reach")  # scripted, deterministic: an episode's outcome depends on its reset seed only
    kwargs = dict(max_steps=45, progress=False, num_points=64)  # 45 steps: some episodes end before success
    full = evaluate(expert, "reach", 4, seed=1, **kwargs).to_dict()["episodes"]
    assert 0 < sum(r["success"] for r in full) < 4
    chosen = evaluate(expert, "reach", 2, seed=1, episode_indices=[3, 1], **kwargs).to_dict()["episodes"]
    assert chosen == [full[3], full[1]] and chosen[0]["reset_seed"] == eval_episode_seed(1, 3)
    seen = []
    stopped = evaluate(
        expert, "reach", 4, seed=1, stop_when=lambda records: seen.append(len(records)) or len(records) == 2, **kwargs
    )
    assert stopped.to_dict()["episodes"] == full[:2] and seen == [1, 2]
