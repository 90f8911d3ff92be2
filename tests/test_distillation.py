"""The distilled point-cloud student (issue 44, part 3): it starts as the policy's encoding, distillation lowers a
held-out ranking loss, it learns from the cloud what only the teacher reads, and it reranks and reloads like the
chunk critic."""

from dataclasses import replace

import pytest
import torch
from conftest import untrained_reach_policy
from tensordict import TensorDict
from test_scorer_benchmark import SIZES, toy_benchmark

from torchrl_dalir.branching.scorer_benchmark import scorer_ladder
from torchrl_dalir.modules import PointCloudCritic, PointCloudCriticModule
from torchrl_dalir.modules.config import executed_slice
from torchrl_dalir.modules.point_cloud_critic import ENCODER_PARTS, policy_encoders
from torchrl_dalir.objectives import CriticDistillationLoss
from torchrl_dalir.training.distillation import DistillationConfig
from torchrl_dalir.training.ranking import RankingTrainingConfig

FAST = DistillationConfig(
    teacher=RankingTrainingConfig(input="privileged_chunk", targets="soft", steps=300, hidden=32),
    hidden=32,
    distill_steps=300,
    finetune_steps=50,
    lr=3e-3,
)


def visible(rows: TensorDict) -> TensorDict:
    """The toy benchmark's decisions with the deciding state coordinate shown in the cloud (its x offset)."""
    cloud = rows["point_cloud"].float() * 0.1
    cloud[..., 0] += 0.5 * rows["privileged_state"][:, :1, None]
    return rows.set("point_cloud", cloud)


def test_the_student_starts_as_the_policys_encoding_and_the_pooled_path_is_the_same():
    policy = untrained_reach_policy()
    critic = PointCloudCritic.from_policy(policy, hidden=16)
    cloud, agent_pos = torch.rand(3, 2, 40, 3), torch.rand(3, 2, 4)
    assert torch.allclose(critic.encode(cloud, agent_pos), policy.encode(cloud, agent_pos), atol=1e-6)
    executed = torch.rand(3, 5, 8, 4)
    pooled = critic.pooled_points(cloud)
    assert torch.equal(critic.scores_pooled(pooled, agent_pos, executed), critic.scores(cloud, agent_pos, executed))
    encoders = policy_encoders(policy)
    critic.point_encoder.point_mlp[0].weight.data.zero_()  # a copy: training the critic leaves the policy alone
    assert torch.equal(
        encoders["weights"]["point_encoder"]["point_mlp.0.weight"], policy.point_encoder.point_mlp[0].weight
    )
    assert set(encoders["weights"]) == set(ENCODER_PARTS)
    with pytest.raises(TypeError, match="ChunkPolicy3D"):
        policy_encoders(object())


def test_distillation_lowers_a_held_out_ranking_loss_on_toy_decisions():
    """A teacher that prefers the chunk whose first action points along the cloud's offset: the student learns
    that ranking on training decisions and ranks held-out ones by it."""
    torch.manual_seed(0)
    rows, _ = toy_benchmark(decisions=160)
    rows = visible(rows)
    teacher = 4.0 * rows["action_chunk"][:, :, 1, 0] * rows["privileged_state"][:, :1]
    critic = PointCloudCritic(2, 4, 4, 8, point_hidden=(16, 32), point_out=16, state_out=8, hidden=32)
    critic.point_normalizer.fit(rows["point_cloud"])
    critic.action_normalizer.fit(rows["action_chunk"][:, :, 1:9])
    decisions = TensorDict(
        point_cloud=rows["point_cloud"],
        agent_pos=rows["agent_pos"],
        executed_actions=rows["action_chunk"][:, :, 1:9],
        teacher_logits=teacher,
        batch_size=[160],
    )
    train, test = decisions[:120], decisions[120:]
    loss = CriticDistillationLoss(PointCloudCriticModule(critic))
    with torch.no_grad():
        before = loss(test)["loss_distillation"].item()
    optimizer = torch.optim.Adam(critic.parameters(), lr=3e-3)
    for step in range(200):
        batch = train[torch.randint(120, (32,))]
        total = sum(loss(batch).values())
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
    with torch.no_grad():
        after = loss(test)["loss_distillation"].item()
        agrees = (
            (
                critic.scores(test["point_cloud"], test["agent_pos"], test["executed_actions"]).argmax(-1)
                == teacher[120:].argmax(-1)
            )
            .float()
            .mean()
            .item()
        )
    assert after < 0.5 * before
    assert agrees > 0.8  # the held-out decisions' teacher pick, from the cloud alone


def test_the_student_learns_from_the_cloud_what_only_the_teacher_reads():
    rows, _ = toy_benchmark()
    rows = visible(rows)
    policy = untrained_reach_policy()
    policy.point_normalizer.fit(rows["point_cloud"])
    distill, _ = toy_benchmark(decisions=200)
    distill = visible(distill).select("point_cloud", "agent_pos", "privileged_state", "action_chunk", "reset_seed")
    ladder = scorer_ladder(
        rows,
        SIZES,
        RankingTrainingConfig(steps=300, hidden=32),
        folds=4,
        scorers={},
        distill=(distill, {"encoders": policy_encoders(policy)}),
        distillation=FAST,
    )
    assert ladder["student"]["states"] == 200
    assert ladder["student"]["auc"] > 0.8  # the clouds show the state; the critic on a noise condition: ~0.5
    assert ladder["student"]["gain"] > 0.2
    unread = torch.ones(distill["action_chunk"].shape[2], dtype=torch.bool)
    unread[executed_slice(SIZES["obs_steps"], SIZES["action_steps"])] = False
    distill["action_chunk"][:, :, unread] = float("nan")  # as a file of executed actions loads
    again = scorer_ladder(
        rows, SIZES, RankingTrainingConfig(steps=300, hidden=32), folds=4, scorers={},
        distill=(distill, {"encoders": policy_encoders(policy)}), distillation=FAST,
    )  # fmt: skip
    assert again["student"] == ladder["student"]  # the student reads the executed actions only
    with pytest.raises(ValueError, match="privileged"):
        replace(FAST, teacher=RankingTrainingConfig(input="state_chunk"))


def test_the_actor_reranks_by_the_student_and_its_checkpoint_reloads_identical(tmp_path):
    from torchrl_dalir import RerankingActor
    from torchrl_dalir.checkpoints import load_chunk_critic, save_chunk_critic

    policy = untrained_reach_policy()
    critic = PointCloudCritic.from_policy(policy, hidden=16)
    critic.action_normalizer.fit(torch.rand(20, 4) * 2 - 1)
    critic.point_encoder.projection[0].weight.data.normal_()  # trained: no longer the policy's encoding
    dalir = RerankingActor(policy, num_candidates=6, critic=critic)
    observation = TensorDict(point_cloud=torch.rand(2, 2, 40, 3), agent_pos=torch.rand(2, 2, 4), batch_size=[2])
    decision = dalir(observation.clone())
    dalir.reset()
    chunks = dalir.sample_candidates(observation["point_cloud"], observation["agent_pos"])
    logits = critic.scores(observation["point_cloud"], observation["agent_pos"], chunks[:, :, 1:9])
    assert torch.allclose(decision["dalir", "candidate_scores"], torch.sigmoid(logits))

    save_chunk_critic(tmp_path / "student.pt", critic, policy, {"held_out_auc": 0.7})
    loaded = load_chunk_critic(tmp_path / "student.pt", policy=policy)
    assert type(loaded) is PointCloudCritic and loaded.metrics == {"held_out_auc": 0.7}
    assert all(torch.equal(a, b) for a, b in zip(loaded.state_dict().values(), critic.state_dict().values()))


def test_a_distillation_file_keeps_one_frame_of_a_first_decision_and_reloads_the_states(tmp_path):
    from torchrl_dalir.branching.scorer_benchmark import distillation_contents, load_distillation, save_benchmark

    policy = untrained_reach_policy()
    rows, _ = toy_benchmark(decisions=6)
    states = rows.select("point_cloud", "agent_pos", "privileged_state", "action_chunk", "reset_seed")
    states["point_cloud"] = states["point_cloud"][:, :1].repeat(1, 2, 1, 1).half()  # a first decision's history
    states["agent_pos"] = states["agent_pos"][:, :1].repeat(1, 2, 1)
    contents = distillation_contents(policy, states)
    assert contents["rows"]["point_cloud"].shape[1] == 1 and contents["history"] == 2
    save_benchmark(tmp_path / "distill.pt", contents)
    stored = torch.load(tmp_path / "distill.pt", weights_only=True)["rows"]
    for key in ("point_cloud", "action_chunk"):  # one float16 frame saved, not the history; executed actions only
        assert stored[key].untyped_storage().nbytes() == stored[key].numel() * 2
    save_benchmark(tmp_path / "compressed.pt", contents, compress=True)
    assert (tmp_path / "compressed.pt").stat().st_size < (tmp_path / "distill.pt").stat().st_size
    loaded, info = load_distillation(tmp_path / "compressed.pt")
    assert torch.equal(loaded["point_cloud"], states["point_cloud"].float())
    assert torch.equal(loaded["agent_pos"], states["agent_pos"])
    executed = executed_slice(policy.obs_steps, policy.action_steps)
    assert loaded["action_chunk"].shape == states["action_chunk"].shape
    assert torch.equal(loaded["action_chunk"][:, :, executed], states["action_chunk"][:, :, executed].half().float())
    unread = torch.ones(states["action_chunk"].shape[2], dtype=torch.bool)
    unread[executed] = False
    assert unread.any() and loaded["action_chunk"][:, :, unread].isnan().all()  # what no scorer reads is NaN
    assert info["task"] == "reach" and set(info["encoders"]["weights"]) == set(ENCODER_PARTS)
    states["agent_pos"][0, 1] += 1  # a later decision: its history is not one frame, and is kept whole
    contents = distillation_contents(policy, states)
    assert contents["rows"]["point_cloud"].shape[1] == 2 and contents["rows"]["agent_pos"].shape[1] == 2
    save_benchmark(tmp_path / "later.pt", contents)
    loaded, _ = load_distillation(tmp_path / "later.pt")
    assert torch.equal(loaded["agent_pos"], states["agent_pos"])
    assert torch.equal(loaded["point_cloud"], states["point_cloud"].float())


def test_the_critic_screen_screens_a_student_distilled_on_a_benchmark(trained_policy, tmp_path):
    import runpy
    from pathlib import Path

    from torchrl_dalir.branching.scorer_benchmark import distillation_contents, distillation_states, save_benchmark
    from torchrl_dalir.checkpoints import load_chunk_critic, load_policy
    from torchrl_dalir.reranking import RerankingConfig

    _, checkpoint = trained_policy
    policy = load_policy(checkpoint)
    reranking = RerankingConfig(num_candidates=4)
    states = distillation_states(policy, 600_000, 10, reranking, progress=False)
    rows = states[:6].clone()  # the benchmark's decisions, with made-up outcomes under 4 draws
    outcomes = torch.rand(6, 4, 4, generator=torch.Generator().manual_seed(0)) < 0.5
    rows.update({"success": outcomes[..., 0], "redraws": outcomes[..., 1:], "decision": torch.zeros(6).long()})
    sizes = {"obs_steps": policy.obs_steps, "action_steps": policy.action_steps, "action_dim": policy.action_dim}
    info = {"format": 1, "task": policy.task, "policy_digest": "0" * 64, "sizes": sizes}
    save_benchmark(tmp_path / "toy.pt", {**info, "rows": rows.to_dict()})
    save_benchmark(tmp_path / "distill" / "toy.pt", distillation_contents(policy, states[6:]))

    main = runpy.run_path(str(Path(__file__).parents[1] / "examples" / "paper" / "critic_screen.py"))["main"]
    argv = [f"policy={checkpoint}", f"student={tmp_path / 'toy.pt'}", "episodes=2", f"out={tmp_path / 'screen'}"]
    argv += ["distillation.distill_steps=5", "distillation.finetune_steps=2", "distillation.teacher.steps=5"]
    with pytest.raises(ValueError, match="not both"):
        main([*argv, f"branched={tmp_path}"])
    result = main([*argv, "progress=false"])
    assert result["student"]["distill_states"] == 4 and "held_out_auc" not in result["student"]
    assert result["reranking"]["num_candidates"] == 4 and result["reranking"]["decisions"] == 1
    base, student = (result["methods"][m]["records"] for m in ("base policy", "critic"))
    assert [r["reset_seed"] for r in base] == [r["reset_seed"] for r in student]
    critic = load_chunk_critic(tmp_path / "screen" / policy.task / Path(checkpoint).parent.name / "critic.pt")
    assert type(critic) is PointCloudCritic


def test_distillation_states_of_later_decisions_are_the_replayed_base_episode(trained_policy):
    from torchrl_dalir.branching.outcome_noise import decision_state
    from torchrl_dalir.branching.scorer_benchmark import distillation_states
    from torchrl_dalir.branching.simulator import candidate_chunks, observation_history
    from torchrl_dalir.checkpoints import load_policy
    from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
    from torchrl_dalir.envs.tasks import get_task
    from torchrl_dalir.reranking import RerankingConfig
    from torchrl_dalir.reranking.candidates import candidate_generator

    policy = load_policy(trained_policy[1])
    reranking = RerankingConfig(num_candidates=3)
    generator = candidate_generator(reranking)
    first = distillation_states(policy, 600_000, 2, reranking, progress=False)
    later = distillation_states(policy, 600_000, 2, reranking, progress=False, decisions=3)
    assert (
        later["decision"].tolist() == [0, 1, 2, 0, 1, 2]
        and later["reset_seed"].tolist() == [600_000] * 3 + [600_001] * 3
    )
    assert (later[later["decision"] == 0] == first).all()  # decisions=1 is the first-decision file's rows
    assert not torch.equal(later["agent_pos"][1], later["agent_pos"][0])  # the robot has moved
    spec = get_task(policy.task)
    env = PointCloudObservation(
        make_simulator(spec), spec, policy.num_points, decision_period=policy.action_steps, history=policy.obs_steps
    )
    for row in later[later["decision"] > 0]:
        _, observations = decision_state(env, policy, int(row["reset_seed"]), int(row["decision"]), "cpu")
        cloud, agent_pos = observation_history(policy, observations, "cpu")
        assert torch.equal(cloud[0].half(), row["point_cloud"]) and torch.equal(agent_pos[0], row["agent_pos"])
        assert torch.equal(torch.as_tensor(observations[-1]["privileged_state"]), row["privileged_state"])
        chunks = candidate_chunks(policy, generator, observations, 3, int(row["reset_seed"]), int(row["decision"]),
                                  reranking.candidates, "cpu")  # fmt: skip
        assert torch.equal(chunks, row["action_chunk"])  # the candidates of that decision's own noise streams
    env.close()
