"""The candidates' ceiling: the oracle's choice, exact replays from saved simulator states, the summary."""

import json
import runpy
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SHORT_REACH, untrained_reach_policy

from torchrl_dalir import keys
from torchrl_dalir.branching.ceiling import (
    candidate_ceiling,
    ceiling_episode,
    oracle_choice,
    summarize_ceiling,
)
from torchrl_dalir.branching.simulator import branch, candidate_chunks, continue_base, executed_actions
from torchrl_dalir.reranking import RerankingConfig, candidate_generator


class LineEnv:
    """A 1-D episode: the action moves ``x``; success once ``x >= 20``; 40 steps at most."""

    def reset(self, seed=None):
        self.x, self.t = 0.0, 0
        return self._observation(), {}

    def _observation(self):
        return {keys.POINT_CLOUD: np.zeros((4, 3), np.float32), keys.AGENT_POS: np.array([self.x], np.float32)}

    def step(self, action):
        self.x, self.t = self.x + float(action[0]), self.t + 1
        success = self.x >= 20
        return self._observation(), 0.0, success, self.t >= 40, {keys.SUCCESS: np.array([success])}

    def get_state(self):
        return (self.x, self.t)

    def set_state(self, state):
        self.x, self.t = state


class ConstantPolicy:
    """Every action of a chunk is the condition's first entry: the clean observation gives 0 (standing still)."""

    horizon, obs_steps, action_steps, action_dim, task, num_points = 16, 2, 8, 1, None, 4

    def encode(self, cloud, agent_pos):
        return torch.zeros(cloud.shape[0], 2)

    def sample(self, cond, generator=None, noise=None):
        return cond[..., :1, None].expand(*cond.shape[:-1], 16, 1)


class IndexGenerator:
    """Candidate k's condition makes the policy act with k at every step."""

    def conditions(self, policy, cloud, agent_pos, num_candidates, generator):
        index = torch.arange(num_candidates, dtype=torch.float32)
        return torch.stack([index, index], -1).expand(cloud.shape[0], -1, -1)


def test_oracle_choice_prefers_the_clean_candidate_then_the_earliest_success():
    assert oracle_choice([True, True], [30, 5]) == 0
    assert oracle_choice([False, False, True, True, True], [40, 40, 12, 7, 7]) == 3
    assert oracle_choice([False, False], [40, 40]) is None


@pytest.mark.parametrize("exhaustive", [False, True])
def test_oracle_executes_the_candidate_whose_branch_succeeds(exhaustive):
    # Standing still fails. Acting with k for 8 steps reaches x = 8k: candidates 3 (x = 21 after 7 steps)
    # and 4 (x = 20 after 5 steps) succeed from the first decision, 1 and 2 do not and then stand still.
    record = ceiling_episode(
        LineEnv(),
        ConstantPolicy(),
        {"index": IndexGenerator()},
        episode_seed=0,
        num_candidates=5,
        exhaustive=exhaustive,
    )
    assert (record["base_success"], record["base_steps"], record["decisions"]) == (False, 40, 5)
    oracle = record["generators"]["index"]
    assert (oracle["success"], oracle["decision"], oracle["candidate"], oracle["steps"], oracle["winners"]) == (
        True,
        0,
        4,
        5,
        2,
    )
    if exhaustive:  # every decision is branched; from decision d, x = 8k after the candidate's 8 steps
        assert oracle["branches"] == 5 * 4
        assert oracle["branch_successes"][0] == [False, False, False, True, True]
        assert all(successes == [False, False, False, True, True] for successes in oracle["branch_successes"][:4])
    else:  # the search stops at the first decision with a winner
        assert oracle["branches"] == 4
    summary = summarize_ceiling([{"episode": 0, **record}])
    assert summary["base_success_rate"] == 0.0
    assert summary["generators"]["index"]["oracle_success_rate"] == 1.0
    assert summary["generators"]["index"]["failures_fixed"] == 1


def test_a_stride_branches_every_stride_th_decision_only():
    # Decisions 0, 2 and 4 of the 5 are branched; candidate 3 fixes the episode from the first one.
    policy, generators = ConstantPolicy(), {"index": IndexGenerator()}
    oracle = ceiling_episode(LineEnv(), policy, generators, episode_seed=0, num_candidates=4, stride=2)["generators"][
        "index"
    ]
    assert (oracle["success"], oracle["decision"], oracle["candidate"], oracle["steps"]) == (True, 0, 3, 7)
    exhaustive = ceiling_episode(
        LineEnv(), policy, generators, episode_seed=0, num_candidates=4, stride=2, exhaustive=True
    )
    assert len(exhaustive["generators"]["index"]["branch_successes"]) == 3  # decisions 0, 2 and 4 of 5


def test_no_winning_candidate_keeps_the_base_policy():
    record = ceiling_episode(LineEnv(), ConstantPolicy(), {"index": IndexGenerator()}, episode_seed=0, num_candidates=3)
    oracle = record["generators"]["index"]
    assert (oracle["success"], oracle["decision"], oracle["candidate"]) == (False, None, None)
    assert oracle["branches"] == 5 * 2  # every decision of the failed episode was tried


def test_summary_exact_values():
    def record(base, oracle, decision=None, winners=None):
        return {
            "base_success": base,
            "generators": {"g": {"success": oracle, "decision": decision, "winners": winners, "branches": 7}},
        }

    summary = summarize_ceiling(
        [record(True, True, 0), record(False, True, 4, 2), record(False, True, 2, 4), record(False, False)]
    )
    assert summary["base_success_rate"] == 0.25
    entry = summary["generators"]["g"]
    assert (entry["oracle_success_rate"], entry["failures_fixed"], entry["failures"]) == (0.75, 2, 3)
    assert (entry["median_fix_decision"], entry["median_winners_at_fix"], entry["headroom"]) == (3.0, 3.0, 0.5)


def test_set_state_replays_the_unbranched_continuation_bit_for_bit():
    from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
    from torchrl_dalir.seeds import eval_episode_seed

    policy, seed = untrained_reach_policy(), eval_episode_seed(1, 0)
    env = PointCloudObservation(make_simulator(SHORT_REACH), SHORT_REACH, 40, decision_period=8, history=2)
    try:
        first, second = [], []
        observation, _ = env.reset(seed=seed)
        outcome = continue_base(
            env, policy, [observation], seed, 0, "cpu", visit=lambda d, obs: first.append((env.get_state(), obs))
        )
        assert len(first) == 10  # 80 steps, a decision every 8
        state, observations = first[3]
        env.set_state(state)
        replay = continue_base(env, policy, observations, seed, 3, "cpu", visit=lambda d, obs: second.append(obs))
        assert replay == (outcome[0], outcome[1] - 3 * 8)
        for (_, original), replayed in zip(first[3:], second, strict=True):
            assert len(original) == len(replayed)
            for a, b in zip(original, replayed):
                for key in (keys.POINT_CLOUD, keys.AGENT_POS, keys.PRIVILEGED_STATE):
                    np.testing.assert_array_equal(a[key], b[key])  # NaN where no decision reads the cloud, in both
        # The clean candidate's branch from decision j is the base episode from there: same outcome, same end state.
        env.set_state(first[0][0])
        continue_base(env, policy, first[0][1], seed, 0, "cpu")
        end = env.get_state().physics
        for j in (0, 3, 7):
            state, observations = first[j]
            chunks = candidate_chunks(
                policy, candidate_generator(RerankingConfig(4)), observations, 4, seed, j, "x", "cpu"
            )
            clean = executed_actions(policy, chunks)[0]
            assert branch(env, policy, state, observations, clean, seed, j, "cpu") == (outcome[0], outcome[1] - 8 * j)
            np.testing.assert_array_equal(env.get_state().physics, end)
            other = branch(env, policy, state, observations, executed_actions(policy, chunks)[1], seed, j, "cpu")
            assert not np.array_equal(env.get_state().physics, end) and other[1] <= outcome[1] - 8 * j
    finally:
        env.close()


def test_ceiling_on_the_simulator_resumes_and_reports_every_generator():
    policy = untrained_reach_policy()
    generators = {name: candidate_generator(RerankingConfig(2, name)) for name in ("dropout", "clean")}
    seen = []
    records = candidate_ceiling(
        policy, SHORT_REACH, generators, episodes=2, num_candidates=2, done=[0], on_episode=seen.append, progress=False
    )
    assert [r["episode"] for r in records] == [1] and seen == records
    outcome = records[0]["generators"]
    assert set(outcome) == {"dropout", "clean"}
    if not records[0]["base_success"]:  # an untrained policy: every decision of the failed episode is branched once
        assert all(o["success"] or o["branches"] == records[0]["decisions"] for o in outcome.values())
    with pytest.raises(ValueError, match="num_candidates"):
        candidate_ceiling(policy, SHORT_REACH, generators, num_candidates=1)


SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "paper" / "candidate_ceiling.py"


def test_script_resumes_after_a_torn_line_and_summarises_the_same(trained_policy, tmp_path):
    _, checkpoint = trained_policy
    main = runpy.run_path(str(SCRIPT))["main"]
    argv = [
        f"policies=[{checkpoint}]",
        "episodes=2",
        "num_candidates=2",
        f"out={tmp_path}",
        "progress=false",
        f"json={tmp_path / 'ceiling.json'}",
    ]
    first = main(argv)
    episodes = tmp_path / "reach" / f"{Path(checkpoint).parent.name}.jsonl"
    lines = episodes.read_text().splitlines()
    assert len(lines) == 3 and json.loads(lines[0])["settings"]["num_candidates"] == 2
    episodes.write_text("\n".join(lines[:2]) + "\n" + lines[2][:20])  # killed while writing episode 1
    assert main(argv) == first  # episode 1 measured again, to the same outcome
    assert json.loads((tmp_path / "ceiling.json").read_text())["runs"] == first
    (partial,) = main([*argv, "episodes=5", "measure=false"])  # summarises the 2 episodes measured, runs none
    assert partial["episodes"] == 2 and len(episodes.read_text().splitlines()) == 3
    with pytest.raises(ValueError, match="was measured with"):
        main([*argv[:2], "num_candidates=3", *argv[3:]])
    with pytest.raises(ValueError, match="test episodes"):
        main([*argv, "seed=0"])
    with pytest.raises(ValueError, match="candidates"):
        main([*argv, "generators=[dropuot]"])
