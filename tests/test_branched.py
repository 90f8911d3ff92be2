"""Branched outcomes (data from the same state) and the scorer that ranks within a state."""

import json
import math
import runpy
from pathlib import Path

import pytest
import torch
from conftest import SHORT_REACH, untrained_reach_policy
from tensordict import TensorDict

from torchrl_dalir.branching import outcomes as branched
from torchrl_dalir.branching.outcomes import BranchedOutcomes, collect_branched
from torchrl_dalir.modules import PolicyConfig, TaskCompletionScorer, make_policy
from torchrl_dalir.objectives.within_state_ranking import WithinStateRankingLoss
from torchrl_dalir.reranking import RerankingConfig
from torchrl_dalir.training.ranking import (
    RankingTrainingConfig,
    cross_validated_auc,
    fit_critic,
    train_ranking_scorer,
)

PAPER_SCRIPTS = Path(__file__).resolve().parents[1] / "examples" / "paper"


def script_main(name: str):
    """The ``main`` of ``examples/paper/<name>.py``."""
    return runpy.run_path(str(PAPER_SCRIPTS / f"{name}.py"))["main"]


def test_ranking_loss_exact_values_and_only_split_decisions_rank():
    loss = WithinStateRankingLoss(torch.nn.Identity(), outcome_weight=0.5)
    logits = torch.tensor([[0.0, 0.0], [3.0, -1.0]])  # the second decision does not split: no ranking term
    out = loss(
        TensorDict(candidate_features=logits, success=torch.tensor([[True, False], [True, True]]), batch_size=[2])
    )
    assert math.isclose(out["loss_ranking"].item(), math.log(2), rel_tol=1e-6)
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, torch.tensor([[1.0, 0.0], [1.0, 1.0]]))
    assert math.isclose(out["loss_outcome"].item(), 0.5 * bce.item(), rel_tol=1e-6)


def test_ranking_loss_prefers_the_winner_on_a_toy_decision():
    # Two states, two candidates each: the winner is the candidate whose feature matches the state's sign.
    torch.manual_seed(0)
    features = torch.tensor([[[1.0, 1.0], [1.0, -1.0]], [[-1.0, 1.0], [-1.0, -1.0]]])
    success = torch.tensor([[True, False], [False, True]])
    scorer = TaskCompletionScorer(2, hidden=16)
    loss = WithinStateRankingLoss(scorer, outcome_weight=0.0)
    batch = TensorDict(candidate_features=features, success=success, batch_size=[2])
    optimizer = torch.optim.Adam(scorer.parameters(), lr=1e-2)
    first = loss(batch)["loss_ranking"].item()
    for _ in range(200):
        optimizer.zero_grad()
        loss(batch)["loss_ranking"].backward()
        optimizer.step()
    assert loss(batch)["loss_ranking"].item() < 0.1 * first
    logits = scorer(features)
    assert logits[0, 0] > logits[0, 1] and logits[1, 1] > logits[1, 0]


def test_branched_stage_resumes_to_identical_rows_after_a_kill(tmp_path, monkeypatch):
    policy = untrained_reach_policy()
    settings = dict(
        reranking=RerankingConfig(3, "clean"), task=SHORT_REACH, episodes=2, stride=4, seed=7, progress=False
    )
    reference = collect_branched(policy, tmp_path / "whole", **settings)
    assert len(reference) == 2 * 3  # 80 steps: decisions 0, 4 and 8 of each episode
    assert reference.rows["action_chunk"].shape == (6, 3, 16, 4) and reference.rows["success"].shape == (6, 3)
    assert reference.rows["decision"].tolist() == [0, 4, 8, 0, 4, 8]
    assert reference.rows["reset_seed"].tolist() == [7, 7, 7, 8, 8, 8]
    failed = ~reference.rows["success"]
    assert (reference.rows["steps_to_success"][failed] == -1).all()

    memmap = branched._memmap_atomically

    def killed(rows, directory):
        if directory.name == "00001":
            raise KeyboardInterrupt
        memmap(rows, directory)

    monkeypatch.setattr(branched, "_memmap_atomically", killed)
    with pytest.raises(KeyboardInterrupt):
        collect_branched(policy, tmp_path / "killed", **settings)
    with pytest.raises(ValueError, match="unfinished"):
        BranchedOutcomes.load(tmp_path / "killed")
    monkeypatch.setattr(branched, "_memmap_atomically", memmap)
    resumed = collect_branched(policy, tmp_path / "killed", **settings)
    assert (resumed.rows == reference.rows).all()
    early = collect_branched(policy, tmp_path / "early", **{**settings, "decisions": 5})  # decisions 0 and 4 only
    assert early.rows["decision"].tolist() == [0, 4, 0, 4]
    assert (early.rows == reference.rows[reference.rows["decision"] < 5]).all()
    with pytest.raises(ValueError, match="another plan"):
        collect_branched(policy, tmp_path / "killed", **{**settings, "stride": 2})


def test_ranking_scorer_trains_and_reports_held_out_auc():
    # Synthetic branched decisions: the winners are the candidates whose first action is largest.
    policy = untrained_reach_policy()
    g = torch.Generator().manual_seed(0)
    chunks = torch.rand(80, 4, 16, 4, generator=g) * 2 - 1
    push = chunks[:, :, 1:9, 0].mean(-1)
    success = push > push.median(dim=1, keepdim=True).values
    rows = TensorDict(
        {
            "point_cloud": torch.rand(80, 2, 40, 3, generator=g),
            "agent_pos": torch.rand(80, 2, 4, generator=g),
            "action_chunk": chunks,
            "success": success,
            "reset_seed": torch.arange(80) // 4,
        },
        [80],
    )
    scorer, metrics = train_ranking_scorer(rows, policy, RankingTrainingConfig(steps=300, hidden=32, seed=0))
    assert metrics["held_out_split_decisions"] == 24 and metrics["train_split_decisions"] == 56
    assert metrics["loss_end"]["loss_ranking"] < metrics["loss_start"]["loss_ranking"]
    assert metrics["held_out_auc"] > 0.8
    cv = cross_validated_auc(rows, policy, RankingTrainingConfig(steps=300, hidden=32, seed=0), folds=4)
    assert (cv["folds"], cv["split_decisions"]) == (4, 80) and cv["auc"] > 0.8  # every decision scored out of fold
    assert cv["oracle_success"] == 1.0 and cv["clean_success"] == success[:, 0].float().mean().item()
    assert cv["pick_success"] > cv["clean_success"] + 0.2  # the arg-max picks winners the clean candidate misses
    critic, fitted = fit_critic(rows, policy, RankingTrainingConfig(steps=300, hidden=32, seed=0), folds=4)
    assert fitted["out_of_fold"]["ranking"] == cv  # the same folds and seeds
    aucs = {v: fitted["out_of_fold"][v]["auc"] for v in ("outcome", "ranking")}
    assert fitted["variant"] == max(aucs, key=aucs.get) and fitted["train_decisions"] == 80  # trained on all
    with pytest.raises(ValueError, match="critic variant"):
        fit_critic(rows, policy, variants=("listwise",))


def test_script_collects_trains_both_variants_and_reruns_from_the_stored_data(trained_policy, tmp_path):
    import json

    _, checkpoint = trained_policy
    main = script_main("branched_ranking")
    argv = [
        f"policy={checkpoint}",
        "episodes=2",
        "num_candidates=2",
        "stride=8",
        "training.steps=5",
        f"out={tmp_path}",
        "progress=false",
        f"json={tmp_path / 'ranking.json'}",
    ]
    first = main([*argv, "learning_curve=[1]"])
    assert set(first["variants"]) == {"ranking", "outcome"} and set(first["learning_curve"][1]) == {
        "ranking",
        "outcome",
    }
    assert 2 <= first["decisions"] <= 2 * 4  # every 8th decision of 2 episodes of at most 200 steps: 0, 8, 16, 24
    stored = json.loads((tmp_path / "ranking.json").read_text())
    assert json.dumps(stored["variants"]) == json.dumps(first["variants"])  # NaN AUC where no held-out decision splits
    again = main(argv)  # the stored outcomes are loaded, not collected again
    assert json.dumps(again["variants"]) == json.dumps(first["variants"])
    with pytest.raises(ValueError, match="candidates"):
        main([*argv, "generator=dropuot"])


def test_actor_selects_by_the_chunk_critic_and_its_checkpoint_reloads_identical(tmp_path):
    from torchrl_dalir import RerankingActor
    from torchrl_dalir.checkpoints import load_chunk_critic, save_chunk_critic
    from torchrl_dalir.modules import ChunkCritic, LatentEncoder, LatentWorldModel
    from torchrl_dalir.reranking import SelectionConfig

    policy = untrained_reach_policy()
    encoder = LatentEncoder.from_policy(policy)
    parts = (
        encoder,
        LatentWorldModel(encoder.latent_dim, 4, 8, hidden=16, layers=1, heads=2),
        TaskCompletionScorer(encoder.latent_dim, hidden=16),
    )
    critic = ChunkCritic(policy.encode(torch.rand(1, 2, 40, 3), torch.rand(1, 2, 4)).shape[-1], 4, 8, hidden=16)
    critic.action_normalizer.fit(torch.rand(20, 4) * 2 - 1)
    with pytest.raises(ValueError, match="needs a chunk critic"):
        RerankingActor(policy, *parts, num_candidates=6, selection=SelectionConfig("argmax", "critic"))
    dalir = RerankingActor(
        policy, *parts, num_candidates=6, critic=critic, selection=SelectionConfig("argmax", "critic")
    )
    observation = TensorDict(point_cloud=torch.rand(2, 2, 40, 3), agent_pos=torch.rand(2, 2, 4), batch_size=[2])
    decision = dalir(observation.clone())
    dalir.reset()
    chunks = dalir.sample_candidates(observation["point_cloud"], observation["agent_pos"])
    logits = critic(policy.encode(observation["point_cloud"], observation["agent_pos"]), chunks[:, :, 1:9])
    assert torch.equal(decision["dalir", "chosen_candidate"], logits.argmax(-1))
    assert torch.allclose(decision["dalir", "candidate_scores"], torch.sigmoid(logits))

    save_chunk_critic(tmp_path / "critic.pt", critic, policy, {"held_out_auc": 0.5})
    loaded = load_chunk_critic(tmp_path / "critic.pt", policy=policy)
    assert loaded.metrics == {"held_out_auc": 0.5}
    assert all(torch.equal(a, b) for a, b in zip(loaded.state_dict().values(), critic.state_dict().values()))
    with pytest.raises(ValueError, match="another policy"):
        load_chunk_critic(
            tmp_path / "critic.pt",
            policy=make_policy(
                PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]), action_dim=4, state_dim=4
            ),
        )


def test_critic_screen_trains_the_better_variant_and_pairs_it_with_the_base_policy(trained_policy, tmp_path):
    import json

    from torchrl_dalir.checkpoints import load_chunk_critic, load_policy

    _, checkpoint = trained_policy
    policy = load_policy(checkpoint)
    collect_branched(
        policy,
        tmp_path / "branched",
        RerankingConfig(num_candidates=2),
        episodes=2,
        stride=1,
        decisions=1,
        seed=7,
        progress=False,
    )
    main = script_main("critic_screen")
    argv = [
        f"policy={checkpoint}",
        f"branched={tmp_path / 'branched'}",
        "episodes=2",
        "folds=2",
        "training.steps=5",
        f"out={tmp_path / 'screen'}",
        "progress=false",
        f"json={tmp_path / 'screen.json'}",
    ]
    with pytest.raises(ValueError, match="test episodes"):
        main([*argv, "seed=0"])
    result = main(argv)
    assert json.loads((tmp_path / "screen.json").read_text())["paired"] == result["paired"]
    assert result["critic"]["variant"] in ("outcome", "ranking") and result["branched"]["rows"] == 2
    base, critic = (result["methods"][m]["records"] for m in ("base policy", "critic"))
    assert [r["reset_seed"] for r in base] == [r["reset_seed"] for r in critic]
    assert result["paired"]["dalir_only"] == sum(c["success"] and not b["success"] for b, c in zip(base, critic))
    assert all(c["details"]["decisions"] == 1 for c in critic)  # the first decision only, then the base policy
    for b, c in zip(base, critic):  # common noise: until the first switch, the critic's episodes are the base's
        if c["details"]["clean_chosen"] < 1:
            break
        assert (c["steps"], c["episode_return"]) == (b["steps"], b["episode_return"])
    run = tmp_path / "screen" / policy.task / Path(checkpoint).parent.name
    assert load_chunk_critic(run / "critic.pt", policy=policy).metrics["variant"] == result["critic"]["variant"]


def test_distance_hinge_exact_values_and_no_hinge_for_the_executed_chunk_itself():
    from torchrl_dalir.modules import ChunkCritic
    from torchrl_dalir.objectives import DistanceHingeLoss

    torch.manual_seed(0)
    critic = ChunkCritic(cond_dim=6, action_dim=4, action_steps=8, hidden=16)
    critic.action_normalizer.fit(torch.rand(50, 4) * 4 - 2)
    cond, executed = torch.randn(5, 6), torch.rand(5, 8, 4)
    label = torch.tensor([1.0, 0, 1, 0, 1])
    same = TensorDict(
        {
            "condition": cond,
            "executed_actions": executed,
            "perturbed_actions": executed.unsqueeze(1).expand(5, 3, 8, 4),
            "terminal_label": label,
        },
        [5],
    )
    losses = DistanceHingeLoss(critic, scale=2.0)(same)
    assert losses["loss_hinge"] == 0  # a chunk at distance 0 sits exactly at the margin
    q = critic(cond, executed.unsqueeze(1))[:, 0]
    torch.testing.assert_close(losses["loss_outcome"], torch.nn.functional.binary_cross_entropy_with_logits(q, label))
    perturbed = executed.unsqueeze(1) + torch.randn(5, 3, 8, 4) * 0.1
    losses = DistanceHingeLoss(critic, scale=2.0, hinge_weight=0.5)(same.set("perturbed_actions", perturbed))
    n = critic.action_normalizer
    distance = (n(perturbed) - n(executed).unsqueeze(1)).pow(2).mean((-2, -1)).sqrt()
    expected = 0.5 * torch.relu(critic(cond, perturbed) - (q.unsqueeze(1) - 2.0 * distance)).mean()
    torch.testing.assert_close(losses["loss_hinge"], expected)


@pytest.mark.parametrize("negatives", ["noise", "policy"])
def test_mixed_data_critic_learns_the_hinge_and_is_scored_on_branched_decisions(collected, trained_policy, negatives):
    from torchrl_dalir.checkpoints import load_policy
    from torchrl_dalir.training.ranking import MixedCriticConfig, critic_auc, train_mixed_critic

    _, checkpoint = trained_policy
    policy = load_policy(checkpoint)
    cfg = MixedCriticConfig(negatives=negatives, num_negatives=3, decisions=40, hidden=32, steps=200, noise_std=0.3)
    critic, metrics = train_mixed_critic(collected, policy, cfg)
    assert metrics["decisions"] == min(40, metrics["decisions"]) and metrics["decisions"] > 10
    start, end = metrics["loss_start"], metrics["loss_end"]
    assert end["loss_hinge"] + end["loss_outcome"] < start["loss_hinge"] + start["loss_outcome"]
    rows = TensorDict(
        {
            "point_cloud": torch.rand(4, 2, 64, 3),
            "agent_pos": torch.rand(4, 2, 4),
            "action_chunk": torch.rand(4, 5, 16, 4) * 2 - 1,
            "success": torch.tensor([[1, 0, 0, 0, 0], [1, 1, 1, 1, 1], [0, 1, 0, 1, 0], [0] * 5]).bool(),
        },
        [4],
    )
    measured = critic_auc(critic, rows, policy)
    assert measured["split_decisions"] == 2 and 0 <= measured["auc"] <= 1


def test_script_measures_imagined_inputs_the_paper_scorers_and_the_no_simulator_critics(
    collected, trained_world_model, tmp_path
):

    _, world_model, checkpoint = trained_world_model
    main = script_main("branched_ranking")
    argv = [
        f"policy={checkpoint}",
        "episodes=2",
        "num_candidates=2",
        "stride=8",
        "training.steps=5",
        "variants=[outcome_imagined]",
        f"out={tmp_path}",
        "progress=false",
    ]
    with pytest.raises(ValueError, match="world_model="):
        main(argv)
    result = main([*argv, f"world_model={world_model}", f"mixed={collected.root}", "mixed_training.steps=5"])
    assert result["variants"]["outcome_imagined"]["config"]["input"] == "imagined"
    assert {"paper_state_scorer", "paper_ensemble_scorer", "clean_first"} <= set(result["reference_aucs"])
    critics = result["mixed_data_critics"]
    assert set(critics) == {"mixed_labels", "mixed_noise_hinge", "mixed_policy_hinge"}
    assert (
        critics["mixed_labels"]["config"]["hinge_weight"] == 0
        and critics["mixed_labels"]["loss_end"]["loss_hinge"] == 0
    )
    assert all(c["split_decisions"] == result["split_decisions"] for c in critics.values())


def test_redrawn_outcomes_reproduce_the_stored_ones_under_their_own_noise(trained_policy, tmp_path, monkeypatch):
    from torchrl_dalir.branching.outcome_noise import oracle_pick, redraw_outcomes, repeatability
    from torchrl_dalir.checkpoints import load_policy

    _, checkpoint = trained_policy
    policy = load_policy(checkpoint)
    outcomes = collect_branched(
        policy,
        tmp_path / "branched",
        RerankingConfig(num_candidates=2),
        episodes=1,
        stride=12,
        seed=11,
        progress=False,
    )
    with pytest.raises(ValueError, match="another policy"):
        BranchedOutcomes.load(tmp_path / "branched", policy=untrained_reach_policy())
    again = redraw_outcomes(policy, outcomes, draw=0, only_split=False, progress=False)
    assert torch.equal(again["success"], outcomes.rows["success"])  # the collection's own noise: the same outcomes
    assert torch.equal(again["decision"], outcomes.rows["decision"]) and len(again) >= 2  # decisions 0 and 12, ...
    # the script: the stored draw, draw 0 again (a check, not a draw) and draw 1 -> an honest ceiling over 2 draws
    argv = [
        f"policy={checkpoint}",
        f"branched={tmp_path / 'branched'}",
        "draws=[0,1]",
        "only_split=false",
        "progress=false",
    ]
    result = script_main("outcome_noise")(argv)
    assert result["honest_ceiling"]["draws"] == 2 and result["honest_ceiling"]["decisions"] == len(again)
    assert [row["second"][0] for row in result["decisions"]] == again["success"].int().tolist()  # draw 0, stored
    # a killed run resumes: draw 1 had finished its first decision only, draw 0 all of them
    from torchrl_dalir.branching import outcome_noise

    draw1 = tmp_path / "branched" / "redraws" / "draw1.json"
    stored = json.loads(draw1.read_text())
    assert len(stored["success"]) == len(again) and stored["plan"]["draw"] == 1
    draw1.write_text(json.dumps({**stored, "success": stored["success"][:1]}))
    branches = []
    real_branch = outcome_noise.branch
    monkeypatch.setattr(outcome_noise, "branch", lambda *a: branches.append(a) or real_branch(*a))
    assert script_main("outcome_noise")(argv)["decisions"] == result["decisions"]  # the same
    assert len(branches) == 2 * (len(again) - 1)  # the unfinished decisions of draw 1, 2 candidates each
    draw1.write_text(json.dumps({**stored, "plan": {**stored["plan"], "draw": 2}}))
    with pytest.raises(ValueError, match="another plan"):
        script_main("outcome_noise")(argv)
    # the teacher's input: the simulator state replayed to each decision, checked against the stored observation
    from torchrl_dalir.branching.outcome_noise import privileged_states
    from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
    from torchrl_dalir.envs.tasks import get_task

    states = privileged_states(policy, outcomes, progress=False)
    spec = get_task(policy.task)
    env = PointCloudObservation(make_simulator(spec), spec, policy.num_points, history=policy.obs_steps)
    at_reset = torch.as_tensor(env.reset(seed=11)[0]["privileged_state"])
    env.close()
    assert states.shape == (len(again), at_reset.shape[0]) and torch.equal(states[0], at_reset)  # decision 0
    assert not torch.equal(states[0], states[1])  # decision 12 is 12 chunks later
    tampered = outcomes.rows.to_tensordict()
    tampered["agent_pos"][1, -1, 0] += 1e-6
    with pytest.raises(ValueError, match="does not give the stored observation"):
        privileged_states(policy, tampered, progress=False)
    first = torch.tensor([[0, 1, 1], [1, 0, 1], [0, 0, 0]]).bool()
    second = torch.tensor([[0, 0, 1], [0, 1, 1], [1, 0, 0]]).bool()
    assert oracle_pick(first).tolist() == [1, 0, 0]  # the first winner; the clean one if it won or none did
    measured = repeatability(first, second)
    assert (measured["win_again"], measured["win_after_loss"]) == pytest.approx((0.5, 0.4))  # 2 of 4, 2 of 5
    assert (measured["clean"], measured["first_draw_oracle_pick"], measured["second_draw_oracle"]) == pytest.approx(
        (1 / 3, 1 / 3, 1)
    )


def test_honest_ceiling_picks_by_the_other_draws_and_cannot_pick_the_lucky_continuation():
    from torchrl_dalir.branching.outcome_noise import honest_ceiling

    # decision 0: candidate 2 wins every draw; decision 1: each candidate wins exactly one draw of three (luck)
    success = torch.zeros(2, 3, 3, dtype=torch.bool)
    success[0, 2] = True
    success[1, [0, 1, 2], [0, 1, 2]] = True
    ceiling = honest_ceiling(success)
    # decision 0: the pick is candidate 2 in every fold (3 of 3); decision 1: the pick is a winner of the other
    # draws (the first of them on a tie), which lost the held-out one (0 of 3)
    assert ceiling["honest"] == pytest.approx(0.5)
    assert ceiling["clean"] == pytest.approx((0 + 1 / 3) / 2)
    assert ceiling["oracle"] == 1.0  # a winner in every draw of both decisions: the clairvoyant pick
    assert ceiling["honest_gain"] == pytest.approx(1 / 3) and ceiling["oracle_gain"] == pytest.approx(5 / 6)
    # per decision: +1 and -1/3; their standard deviation 4 / (3 sqrt 2), over sqrt 2 decisions
    assert ceiling["honest_gain_se"] == pytest.approx(2 / 3)
    # both split in every held-out draw: decision 0's winner has the best mean elsewhere (AUC 1), decision 1's
    # won nothing else (AUC 0)
    assert ceiling["true_chance_auc"] == 0.5
    with pytest.raises(ValueError, match="at least 2 draws"):
        honest_ceiling(success[..., :1])


def test_the_honest_ceiling_by_decision_is_the_ceiling_of_each_decision_index_apart():
    from torchrl_dalir.branching.outcome_noise import honest_ceiling, honest_ceiling_by_decision

    success = torch.rand(6, 4, 3, generator=torch.Generator().manual_seed(0)) > 0.5
    decision = torch.tensor([0, 1, 0, 2, 1, 0])
    by_decision = honest_ceiling_by_decision(success, decision)
    assert sorted(by_decision) == [0, 1, 2] and by_decision[0]["decisions"] == 3
    assert by_decision[1] == honest_ceiling(success[[1, 4]])
    # decision 0's rows weigh 3 of 6 in the pooled ceiling: the pooled gain is the rows' weighted mean
    pooled = sum(c["honest_gain"] * c["decisions"] for c in by_decision.values()) / len(success)
    assert honest_ceiling(success)["honest_gain"] == pytest.approx(pooled)
    with pytest.raises(ValueError, match="each of the 6 rows"):
        honest_ceiling_by_decision(success, decision[:5])


def test_the_honest_ceiling_by_candidates_uses_the_first_k_of_them():
    from torchrl_dalir.branching.outcome_noise import honest_ceiling, honest_ceiling_by_candidates

    success = torch.rand(5, 12, 3, generator=torch.Generator().manual_seed(0)) > 0.5
    by_candidates = honest_ceiling_by_candidates(success)
    assert list(by_candidates) == [2, 4, 8, 12]
    assert by_candidates[4] == honest_ceiling(success[:, :4]) and by_candidates[12] == honest_ceiling(success)
    assert list(honest_ceiling_by_candidates(success[:, :8])) == [2, 4, 8]
