"""Selection rules, the scorer ensemble, and calibration on validation episodes."""

import warnings

import pytest
import torch
from tensordict import TensorDict

from torchrl_dalir import RerankingActor, keys
from torchrl_dalir.checkpoints import load_world_model, store_selection
from torchrl_dalir.evaluation import calibration
from torchrl_dalir.modules import ScorerEnsemble, TaskCompletionScorer
from torchrl_dalir.objectives import ImaginedCompletionLoss
from torchrl_dalir.reranking.random_choice import RandomCandidateActor
from torchrl_dalir.reranking.selection import SelectionConfig, select

# one decision, 3 ensemble members, 4 candidates (0 is the clean one)
MEMBERS = torch.tensor(
    [
        [
            [0.10, 0.30, 0.155, 0.05],
            [0.10, 0.10, 0.145, 0.05],
            [0.10, 0.05, 0.135, 0.05],
        ]
    ]
)  # candidate 1: the best mean (0.150), members disagree (std 0.108); candidate 2: 0.145, std 0.008


def test_each_rule_makes_the_expected_choice():
    assert select(MEMBERS, SelectionConfig("argmax")).item() == 1
    assert select(MEMBERS, SelectionConfig("pessimistic", k=1.0)).item() == 2  # 0.137 against 0.042 for candidate 1
    assert select(MEMBERS, SelectionConfig("pessimistic", k=0.0)).item() == 1
    # candidate 2's advantage over the clean one is 0.045 +- 0.0082: lower bound 0.0368
    assert select(MEMBERS, SelectionConfig("margin", k=1.0, margin=0.035)).item() == 2
    assert select(MEMBERS, SelectionConfig("margin", k=1.0, margin=0.04)).item() == 0
    assert select(MEMBERS, SelectionConfig("margin", k=0.0, margin=0.04)).item() == 1  # no pessimism: 0.05 > 0.04
    assert select(MEMBERS, SelectionConfig("margin", k=1.0, margin=1.0)).item() == 0


def test_only_a_margin_of_at_least_one_keeps_the_clean_candidate_whatever_the_scores():
    assert [SelectionConfig("margin", margin=m).keeps_clean for m in (1.0, 2.0, 0.99)] == [True, True, False]
    assert not SelectionConfig("argmax").keeps_clean and not SelectionConfig("pessimistic", k=1.0).keeps_clean
    # the most extreme probabilities: the clean candidate 0, another 1, in every member
    extreme = torch.tensor([[[0.0, 1.0, 0.5]] * 3])
    assert select(extreme, SelectionConfig("margin", margin=1.0)).item() == 0
    assert select(extreme, SelectionConfig("margin", margin=0.99)).item() == 1
    worse = torch.tensor([[[0.5, 0.4, 0.3]]])  # every other candidate scores below the clean one
    assert select(worse, SelectionConfig("margin", margin=0.0)).item() == 0


def test_margin_without_pessimism_or_margin_is_the_argmax():
    scores = torch.rand(500, 1, 32, generator=torch.Generator().manual_seed(0))
    assert torch.equal(
        select(scores, SelectionConfig("margin", k=0.0, margin=0.0)), select(scores, SelectionConfig("argmax"))
    )


def test_softmax_samples_in_proportion_and_tends_to_the_argmax():
    scores = torch.tensor([[[0.10, 0.12, 0.11]]]).expand(20000, 1, 3)
    config = SelectionConfig("softmax", temperature=0.01)
    counts = torch.bincount(select(scores, config, torch.Generator().manual_seed(0)), minlength=3).float() / 20000
    torch.testing.assert_close(counts, torch.softmax(torch.tensor([10.0, 12.0, 11.0]), 0), atol=0.01, rtol=0)
    cold = select(scores[:100], SelectionConfig("softmax", temperature=1e-4), torch.Generator().manual_seed(0))
    assert (cold == 1).all()


def test_trust_chooses_the_best_score_among_the_candidates_nearest_their_mean():
    generator = torch.Generator().manual_seed(0)
    scores, actions = torch.rand(200, 1, 8, generator=generator), torch.randn(200, 8, 4, 3, generator=generator)
    assert torch.equal(
        select(scores, SelectionConfig("trust", fraction=1.0), actions=actions),
        select(scores, SelectionConfig("argmax")),
    )
    distance = (actions - actions.mean(1, keepdim=True)).flatten(2).norm(dim=-1)
    assert torch.equal(
        select(scores, SelectionConfig("trust", fraction=0.1), actions=actions), distance.argmin(-1)
    )  # one kept: the medoid
    half = select(scores, SelectionConfig("trust", fraction=0.5), actions=actions)
    rank = distance.argsort(-1).argsort(-1)  # 0 for the nearest
    assert (rank.gather(-1, half[:, None]) < 4).all()  # among the 4 nearest ...
    best = scores[:, 0].masked_fill(rank >= 4, -1).argmax(-1)
    assert torch.equal(half, best)  # ... the best score
    # the outlier's high score is passed over for the best of the typical ones
    outlier = torch.tensor([[[[0.0]], [[0.2]], [[5.0]], [[0.1]]]])
    assert (
        select(torch.tensor([[[0.1, 0.3, 0.9, 0.2]]]), SelectionConfig("trust", fraction=0.75), actions=outlier).item()
        == 1
    )


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="selection rule must be one of"):
        SelectionConfig("best")
    with pytest.raises(ValueError, match="selection scorer must be one of"):
        SelectionConfig(scorer="oracle")
    with pytest.raises(ValueError, match="temperature > 0"):
        SelectionConfig("softmax", temperature=0.0)
    with pytest.raises(ValueError, match=r"\[batch, members, candidates\]"):
        select(torch.rand(2, 4), SelectionConfig())
    with pytest.raises(ValueError, match=r"fraction in \(0, 1\]"):
        SelectionConfig("trust", fraction=0.0)
    with pytest.raises(ValueError, match="needs the candidates' actions"):
        select(torch.rand(2, 1, 4), SelectionConfig("trust", fraction=0.5))


def test_ensemble_members_are_independent_scorers():
    ensemble = ScorerEnsemble(16, hidden=8, members=3)
    latents = torch.randn(5, 16)
    logits = ensemble(latents)
    for e in range(3):  # member e is a TaskCompletionScorer with the e-th set of weights
        scorer = TaskCompletionScorer(16, hidden=8)
        params = ensemble.ensemble.params_td[e]["module"]
        scorer.load_state_dict({name: value for name, value in params.flatten_keys(".").items()})
        torch.testing.assert_close(scorer(latents), logits[e])
    assert not torch.allclose(logits[0], logits[1])  # different initialisations
    per_member = ensemble(latents.expand(3, 5, 16), per_member=True)
    torch.testing.assert_close(per_member, logits)
    copy = ScorerEnsemble(16, hidden=8, members=3)
    copy.load_state_dict(ensemble.state_dict())
    assert torch.equal(copy(latents), logits)
    with pytest.raises(ValueError, match="expected latents"):
        ensemble(torch.randn(2, 5, 16), per_member=True)


def test_imagined_completion_loss_falls():
    torch.manual_seed(0)
    ensemble = ScorerEnsemble(8, hidden=16, members=2)
    latent = torch.randn(2, 64, 8)
    target = (latent[..., 0] > 0).float()  # learnable from the latent
    batch = TensorDict({"imagined_latent": latent, "future": {keys.COMPLETION_TARGET: target}}, [2, 64])
    loss = ImaginedCompletionLoss(ensemble)
    optimizer = torch.optim.Adam(ensemble.parameters(), lr=1e-2)
    values = []
    for _ in range(60):
        value = loss(batch)["loss_imagined_completion"]
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
        values.append(value.item())
    assert values[-1] < 0.5 * values[0]


def test_actor_member_scores_and_mean(trained_world_model):
    _, wm_path, policy_path = trained_world_model
    parts = load_world_model(wm_path)
    assert parts.ensemble is not None and parts.selection == SelectionConfig()  # the paper's arg-max until calibrated
    actor = RerankingActor.from_checkpoints(
        policy_path, wm_path, num_candidates=4, selection=SelectionConfig("pessimistic", "ensemble", k=1.0)
    )
    cloud, agent_pos = torch.rand(2, 2, 64, 3), torch.rand(2, 2, 4)
    chunks = actor.sample_candidates(cloud, agent_pos)
    members = actor.member_scores(cloud, agent_pos, chunks)
    imagined = actor.imagine(cloud, agent_pos, chunks)
    assert members.shape == (2, parts.ensemble.members, 4)
    torch.testing.assert_close(members, torch.sigmoid(parts.ensemble(imagined)).transpose(0, 1))


def test_default_argmax_makes_the_choice_of_the_paper(trained_world_model):
    _, wm_path, policy_path = trained_world_model
    obs = TensorDict({keys.POINT_CLOUD: torch.rand(3, 2, 64, 3), keys.AGENT_POS: torch.rand(3, 2, 4)}, [3])
    actor = RerankingActor.from_checkpoints(policy_path, wm_path, num_candidates=8, seed=3)
    chosen = actor(obs.clone())["dalir", "chosen_candidate"]
    reference = RerankingActor.from_checkpoints(policy_path, wm_path, num_candidates=8, seed=3)
    chunks, scores = reference.propose(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS])  # the state scorer's probabilities
    torch.testing.assert_close(
        scores, torch.sigmoid(reference.scorer(reference.imagine(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS], chunks)))
    )
    assert torch.equal(chosen, scores.argmax(-1))


def test_actor_trust_rule_reads_the_executed_actions(trained_world_model):
    _, wm_path, policy_path = trained_world_model
    obs = TensorDict({keys.POINT_CLOUD: torch.rand(3, 2, 64, 3), keys.AGENT_POS: torch.rand(3, 2, 4)}, [3])
    medoid = SelectionConfig("trust", fraction=1 / 8)
    chosen = RerankingActor.from_checkpoints(policy_path, wm_path, num_candidates=8, seed=3, selection=medoid)(
        obs.clone()
    )["dalir", "chosen_candidate"]
    reference = RerankingActor.from_checkpoints(policy_path, wm_path, num_candidates=8, seed=3)
    executed = reference.sample_candidates(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS])[
        ..., reference.policy.config.executed, :
    ]
    assert torch.equal(chosen, (executed - executed.mean(1, keepdim=True)).flatten(2).norm(dim=-1).argmin(-1))


def test_ensemble_rule_needs_an_ensemble(trained_world_model):
    _, wm_path, policy_path = trained_world_model
    actor = RerankingActor.from_checkpoints(policy_path, wm_path)
    with pytest.raises(ValueError, match="needs a scorer ensemble"):
        RerankingActor(
            actor.policy,
            actor.encoder,
            actor.world_model,
            actor.scorer,
            selection=SelectionConfig("argmax", "ensemble"),
        )


def test_calibration_reads_only_validation_episodes_and_stores_its_choice(trained_world_model, monkeypatch, tmp_path):
    import shutil

    _, wm_path, policy_path = trained_world_model
    path = tmp_path / "world_model.pt"
    shutil.copy(wm_path, path)
    with pytest.raises(ValueError, match="must not read the test episodes"):
        calibration.calibrate(policy_path, path, seed=calibration.TEST_SEED)
    seeds, rates = (
        [],
        {
            "margin(ensemble, k=1, margin=1)": 0.1,
            "margin(ensemble, k=1, margin=0.02)": 0.6,
            "margin(ensemble, k=1, margin=0)": 0.6,
            "argmax(state)": 0.9,
        },
    )

    def fake_evaluate(policy, world_model, *, methods, episodes, seed, selection=None, **kwargs):
        seeds.append(seed)
        rate = 0.4 if selection is None else rates[selection.name]
        name = "base policy" if methods == ["base"] else "DALI-R"
        records = [{"success": i < rate * episodes} for i in range(episodes)]
        return {name: {"success_rate": rate, "records": records, "seconds": 7.0}}  # margin 1 run would give 0.1, 7 s

    monkeypatch.setattr(calibration, "evaluate_checkpoints", fake_evaluate)
    grid = (
        SelectionConfig("margin", "ensemble", k=1.0, margin=1.0),
        SelectionConfig("margin", "ensemble", k=1.0, margin=0.02),
        SelectionConfig("margin", "ensemble", k=1.0, margin=0.0),
        SelectionConfig("argmax", "state"),
    )
    record = calibration.calibrate(policy_path, path, grid=grid, episodes=10, seed=1, write=False)
    assert record["chosen"] == "argmax(state)"  # the best entry of the grid: 5 episodes won, none lost (p = 0.03)
    assert (
        load_world_model(path).selection == SelectionConfig() and load_world_model(path).calibration is None
    )  # write=False
    seeds.clear()
    record = calibration.calibrate(policy_path, path, grid=grid, rule="margin", episodes=10, seed=1, alpha=1.0)
    assert set(seeds) == {1} and len(seeds) == len(grid)  # the base policy and every entry but margin 1, its replay
    assert record["entries"][0]["success_rate"] == 0.4 and record["entries"][0]["seconds"] == 0.0
    # the best margin setting, the first of two equals; argmax(state) scored more but is not of the rule
    assert record["chosen"] == "margin(ensemble, k=1, margin=0.02)"
    assert record["entries"][1]["vs_base"] == {"base_only": 0, "dalir_only": 2, "p_value": 0.5}
    parts = load_world_model(path)
    assert parts.selection == grid[1] and parts.calibration["chosen"] == record["chosen"]
    assert RerankingActor.from_checkpoints(policy_path, path).selection == grid[1]  # the checkpoint names the default
    store_selection(path, grid[0])  # calibration kept the base policy: the actor says so unless a rule is passed
    with pytest.warns(UserWarning, match="always keeps the clean candidate"):
        assert RerankingActor.from_checkpoints(policy_path, path).selection == grid[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert RerankingActor.from_checkpoints(policy_path, path, selection=grid[3]).selection == grid[3]
        RandomCandidateActor.from_checkpoints(policy_path, path)  # the random control ignores the rule: no warning
    assert (
        RerankingActor.from_checkpoints(policy_path, path, selection=SelectionConfig()).selection == SelectionConfig()
    )
    # with the default evidence rule, 2 episodes won and none lost (one-sided p = 0.25) do not leave the base policy
    record = calibration.calibrate(policy_path, path, grid=grid, rule="margin", episodes=10, seed=1, write=False)
    assert record["chosen"] == "margin(ensemble, k=1, margin=1)" and record["alpha"] == calibration.ALPHA
    with pytest.raises(ValueError, match="alpha is a p-value threshold"):
        calibration.calibrate(policy_path, path, alpha=0.0)


def test_calibration_leaves_the_base_policy_only_with_evidence():
    def entry(name, rate, base_only, dalir_only, rule="margin"):
        return {
            "name": name,
            "selection": {"rule": rule},
            "success_rate": rate,
            "vs_base": {"base_only": base_only, "dalir_only": dalir_only},
        }

    entries = [
        entry("m1", 0.5, 0, 0),
        entry("m0.02", 0.6, 0, 3),
        entry("m0", 0.65, 1, 6),
        entry("argmax", 0.7, 2, 8, rule="argmax"),
    ]
    # one-sided p: 3 / 0 -> 0.125, 6 / 1 -> 0.0625, 8 / 2 -> 0.0547
    assert calibration.choose(entries)["name"] == "argmax"
    assert calibration.choose(entries, rule="margin")["name"] == "m0"
    assert (
        calibration.choose(entries, alpha=0.06)["name"] == "argmax"
        and calibration.choose(entries, rule="margin", alpha=0.06)["name"] == "m1"
    )
    assert calibration.choose(entries, rule="margin", alpha=1.0)["name"] == "m0"
    assert (
        calibration.choose([entry("m1", 0.5, 0, 0), entry("m0", 0.5, 0, 4)], alpha=1.0)["name"] == "m1"
    )  # ties: the first
    assert calibration.choose([entry("m1", 0.5, 0, 0), entry("m0", 0.3, 6, 0)])["name"] == "m1"


def test_calibration_keeps_a_chosen_rule_only_if_fresh_validation_episodes_confirm_it(monkeypatch):
    from types import SimpleNamespace

    from torchrl_dalir.evaluation.compare import BASE, DALIR

    grid = calibration.GRIDS["argmax"]  # one alternative: the base policy (margin 1) or the ensemble arg-max
    assert grid == (SelectionConfig("margin", "ensemble", k=1.0, margin=1.0), SelectionConfig("argmax", "ensemble"))
    outcomes = {  # (evaluation seed, rule) -> successes of 8 episodes; the arg-max wins 4 / 0 on seed 1
        (1, None): "11000000",
        (1, "margin"): "11000000",
        (1, "argmax"): "11111100",
        (2, None): "10100000",
        (2, "argmax"): "10100000",  # ... and ties on the fresh seed 2
        (3, None): "00000000",
        (3, "argmax"): "11110000",  # ... and wins again on seed 3
    }
    calls = []

    def fake_evaluate(policy_path, world_model_path, *, methods, seed, episodes, selection=None, **kwargs):
        calls.append((seed, episodes, tuple(methods)))
        names = {"base": (BASE, None), "dalir": (DALIR, selection.rule if selection else None)}
        return {
            names[m][0]: {
                "success_rate": outcomes[seed, names[m][1]].count("1") / 8,
                "seconds": 0.0,
                "records": [{"success": c == "1"} for c in outcomes[seed, names[m][1]]],
            }
            for m in methods
        }

    monkeypatch.setattr(calibration, "evaluate_checkpoints", fake_evaluate)
    monkeypatch.setattr(calibration, "load_world_model", lambda path: SimpleNamespace(ensemble=object()))
    plain = calibration.calibrate("p.pt", "w.pt", grid=grid, episodes=8, seed=1, write=False)
    assert plain["chosen"] == "argmax(ensemble)" and "confirmation" not in plain and {c[0] for c in calls} == {1}
    calls.clear()
    tied = calibration.calibrate("p.pt", "w.pt", grid=grid, episodes=8, seed=1, write=False, confirm_episodes=8)
    assert tied["chosen"] == grid[0].name and tied["confirmation"]["confirmed"] is False  # the base policy is kept
    assert tied["confirmation"]["vs_base"] == {"base_only": 0, "dalir_only": 0, "p_value": 1.0} and calls[-1] == (
        2,
        8,
        ("base", "dalir"),
    )
    again = calibration.calibrate(
        "p.pt", "w.pt", grid=grid, episodes=8, seed=1, write=False, confirm_episodes=8, confirm_seed=3, alpha=0.1
    )
    assert (
        again["chosen"] == "argmax(ensemble)" and again["confirmation"]["confirmed"] is True
    )  # 4 / 0: one-sided p = 0.0625
    with pytest.raises(ValueError, match="must not read the test episodes"):
        calibration.calibrate("p.pt", "w.pt", grid=grid, seed=1, confirm_episodes=8, confirm_seed=0)
    with pytest.raises(ValueError, match="fresh validation episodes"):
        calibration.calibrate("p.pt", "w.pt", grid=grid, seed=1, confirm_episodes=8, confirm_seed=1)


def test_calibration_sized_by_failures_screens_on_the_base_policys_failures_and_confirms_on_fresh_episodes(monkeypatch):
    from types import SimpleNamespace

    from torchrl_dalir.evaluation.compare import BASE, DALIR

    grid = (
        SelectionConfig("margin", "ensemble", margin=1.0),
        SelectionConfig("argmax", "ensemble"),
        SelectionConfig("softmax", "ensemble"),
    )
    base = {1: "1111111110111111110111110111111111111111", 2: "10" * 20, 3: "10" * 20, 4: "1" * 40}
    solves = {  # rule -> seed -> the episodes it solves
        "argmax": {1: set(range(40)), 2: set(range(40)), 3: {i for i in range(40) if i % 2 == 0}},
        "softmax": {
            1: set(range(1, 40)) - {18, 24}
        },  # of the screen's episodes: one failure (9) solved, one success (0) lost
    }
    calls = []

    def fake_evaluate(
        policy_path,
        world_model_path,
        *,
        methods,
        seed,
        episodes,
        selection=None,
        episode_indices=None,
        stop_when=None,
        **kwargs,
    ):
        rows = {}
        for method in methods:
            rule = selection.rule if method == "dalir" else None
            calls.append((seed, rule, episodes, episode_indices))
            records = []
            for i in episode_indices if episode_indices is not None else range(episodes):
                records.append(
                    SimpleNamespace(
                        episode=i, success=base[seed][i] == "1" if rule is None else i in solves[rule][seed]
                    )
                )
                if stop_when is not None and stop_when(records):
                    break
            rows[BASE if rule is None else DALIR] = {
                "success_rate": sum(r.success for r in records) / len(records),
                "episodes": len(records),
                "seconds": 0.0,
                "records": [vars(r) for r in records],
            }
        return rows

    monkeypatch.setattr(calibration, "evaluate_checkpoints", fake_evaluate)
    monkeypatch.setattr(calibration, "load_world_model", lambda path: SimpleNamespace(ensemble=object()))
    record = calibration.calibrate_on_failures(
        "p.pt", "w.pt", grid=grid, failures=3, min_episodes=20, max_episodes=40, block=10, seed=1, write=False
    )
    # the screen stops at the end of the block holding the third failure (episode 24): 30 episodes
    assert record["episodes"] == 30 and record["failed"] == [9, 18, 24] and record["solved"] == [0, 1, 2]
    assert calls[0] == (1, None, 40, None) and calls[1] == (1, "argmax", 6, [9, 18, 24, 0, 1, 2])  # margin 1 is not run
    argmax, softmax = record["entries"]
    assert (argmax["wins"], argmax["losses"]) == (3, 0) and argmax["estimated_gain"] == pytest.approx(3 / 30)
    assert (softmax["wins"], softmax["losses"]) == (1, 1) and softmax["estimated_gain"] == pytest.approx(
        1 / 3 * 0.1 - 1 / 3 * 0.9
    )
    # the confirmation: as many episodes of seed 2 as the screen took; the arg-max wins all 15 the base policy fails
    assert calls[-2:] == [(2, None, 30, None), (2, "argmax", 30, None)]
    assert (
        record["confirmation"]["vs_base"] == {"base_only": 0, "dalir_only": 15, "p_value": 2 * 0.5**15}
        and record["chosen"] == "argmax(ensemble)"
    )
    tied = calibration.calibrate_on_failures(
        "p.pt",
        "w.pt",
        grid=grid,
        failures=3,
        min_episodes=20,
        max_episodes=40,
        block=10,
        seed=1,
        confirm_seed=3,
        write=False,
    )
    assert (
        tied["confirmation"]["confirmed"] is False and tied["chosen"] == grid[0].name
    )  # 0 / 0 on seed 3: the base policy is kept
    calls.clear()
    easy = calibration.calibrate_on_failures(
        "p.pt", "w.pt", grid=grid, failures=3, min_episodes=20, max_episodes=40, seed=4, confirm_seed=2, write=False
    )
    assert (
        easy["failed"] == [] and easy["entries"] == [] and "confirmation" not in easy and len(calls) == 1
    )  # nothing to screen on
    with pytest.raises(ValueError, match="must not read the test episodes"):
        calibration.calibrate_on_failures("p.pt", "w.pt", grid=grid, seed=1, confirm_seed=0)
    with pytest.raises(ValueError, match="failures"):
        calibration.calibrate_on_failures("p.pt", "w.pt", grid=grid, failures=0)
    with pytest.raises(ValueError, match="max_episodes"):
        calibration.calibrate_on_failures("p.pt", "w.pt", grid=grid, max_episodes=20)  # fewer than min_episodes
    # a base policy that fails early still runs min_episodes: the confirmation is as long
    early = calibration.calibrate_on_failures(
        "p.pt", "w.pt", grid=grid[:2], failures=1, max_episodes=40, seed=2, confirm_seed=3, write=False
    )
    assert early["episodes"] == 30 and early["confirmation"]["episodes"] == 30


def test_calibration_sized_by_failures_runs_on_real_checkpoints(trained_world_model):
    _, wm_path, policy_path = trained_world_model
    grid = (SelectionConfig("margin", "ensemble", margin=1.0), SelectionConfig("argmax", "state"))
    record = calibration.calibrate_on_failures(
        policy_path,
        wm_path,
        grid=grid,
        failures=1,
        min_episodes=2,
        max_episodes=4,
        block=2,
        seed=1,
        write=False,
        num_candidates=3,
        max_steps=10,
        progress=False,
    )
    assert record["episodes"] == 2 and len(record["failed"]) >= 1  # 10 steps: no episode succeeds
    assert [e["name"] for e in record["entries"]] == ["argmax(state)"] and record["entries"][0]["wins"] == 0
    assert record["chosen"] == grid[0].name and "confirmation" not in record  # no estimated gain: nothing to confirm


def test_a_checkpoint_without_an_ensemble_keeps_the_paper_rule_and_refuses_ensemble_rules(
    trained_world_model, tmp_path
):
    _, wm_path, policy_path = trained_world_model
    state = torch.load(wm_path, weights_only=False)
    for key in ("ensemble_state", "ensemble_args", "selection"):  # as written before version 0.2.0
        del state[key]
    old = tmp_path / "old.pt"
    torch.save(state, old)
    parts = load_world_model(old)
    assert parts.ensemble is None and parts.selection == SelectionConfig() and parts.calibration is None
    assert RerankingActor.from_checkpoints(policy_path, old, num_candidates=2).selection == SelectionConfig()
    with pytest.raises(ValueError, match="no scorer ensemble"):  # before any validation episode
        calibration.calibrate(policy_path, old, episodes=1)


def test_the_main_job_refuses_to_calibrate_on_its_test_episodes():
    from torchrl_dalir.pipeline import PipelineConfig

    with pytest.raises(ValueError, match="calibration_seed must differ from eval_seed"):
        PipelineConfig(calibration_seed=0)
    with pytest.raises(ValueError, match="calibration_grid must be one of"):
        PipelineConfig(calibration_grid="everything")
