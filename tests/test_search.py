"""Action-space candidate search (Table 2) on a hand-made world model and scorer with a known optimum."""

import pytest
import torch
from test_reranking import _observation, _parts
from torch import nn

from torchrl_dalir import RerankingActor, keys
from torchrl_dalir.modules import ScorerEnsemble
from torchrl_dalir.reranking import CANDIDATE_SCORES, CHOSEN_CANDIDATE, CleanObservation, SearchConfig
from torchrl_dalir.reranking.search import action_bounds
from torchrl_dalir.reranking.selection import SelectionConfig

METHODS = ["shooting", "cem", "mppi", "gradient"]
STEPS, ACTION_DIM = 8, 4


class ActionsAsLatent(nn.Module):
    """An identity-like world model: the imagined latent holds the executed actions themselves."""

    def __init__(self, latent_dim: int):
        super().__init__()
        self.latent_dim, self.action_dim, self.action_steps = latent_dim, ACTION_DIM, STEPS

    def imagine(self, latent, actions):
        return torch.cat([actions.flatten(-2), latent[..., STEPS * ACTION_DIM :]], -1)


class DistanceScorer(nn.Module):
    """Logit ``-mean((a - target)^2)`` of the imagined actions: the optimum is ``target``, clamped to the bounds."""

    def __init__(self, target: torch.Tensor):
        super().__init__()
        self.register_buffer("target", target.flatten())

    def forward(self, latent):
        return -(latent[..., : self.target.numel()] - self.target).pow(2).mean(-1)


def _target():
    target = torch.full((STEPS, ACTION_DIM), 0.3)
    target[:, 0] = 1.5  # outside the policy's action range: the search must stop at its bound
    return target


def _actor(method, seed=3, num_candidates=8, **settings):
    policy, encoder, _, _ = _parts()
    world_model, scorer = ActionsAsLatent(encoder.latent_dim), DistanceScorer(_target())
    search = SearchConfig(method, **settings)
    return RerankingActor(
        policy,
        encoder,
        world_model,
        scorer,
        num_candidates=num_candidates,
        candidates=CleanObservation(),
        search=search,
        seed=seed,
    )


def _seeds(actor, cloud, agent_pos, seed=3):
    """The policy samples the actor's search starts from (its generator's first draws)."""
    g = torch.Generator().manual_seed(seed)
    return actor.policy.sample(
        CleanObservation().conditions(actor.policy, cloud, agent_pos, actor.num_candidates, g), g
    )


@pytest.mark.parametrize("method", METHODS)
def test_search_improves_the_score_stays_in_bounds_and_keeps_the_clean_sample(method):
    actor = _actor(method, fixed_dims=[3])
    obs = _observation()
    cloud, agent_pos = obs[keys.POINT_CLOUD], obs[keys.AGENT_POS]
    executed = actor.policy.config.executed
    seeds = _seeds(actor, cloud, agent_pos)
    candidates = actor.sample_candidates(cloud, agent_pos)
    assert candidates.shape == seeds.shape == (3, 8, 16, ACTION_DIM)
    assert torch.equal(candidates[:, 0], seeds[:, 0])  # the clean policy sample, untouched
    objective = actor.objective(cloud, agent_pos)
    before, after = objective(seeds[:, :, executed]), objective(candidates[:, :, executed])
    assert (after.max(1).values > before.max(1).values + 0.01).all()
    if method == "gradient":  # every seed ascends
        assert (after[:, 1:] >= before[:, 1:]).all()
    normalizer = actor.policy.action_normalizer
    low, high = normalizer.low, normalizer.high
    assert (candidates[:, 1:] >= low - 1e-5).all() and (candidates[:, 1:] <= high + 1e-5).all()
    assert (seeds[:, 1:] < low - 1e-3).any() or (seeds[:, 1:] > high + 1e-3).any()  # the seeds needed projecting
    # the gripper (dimension 3) keeps a seed's value: the search moved the other dimensions only
    projected = normalizer.unnormalize(normalizer(seeds).clamp(*action_bounds(normalizer)))[:, :, executed, 3]
    searched = candidates[:, 1:, executed, 3]
    matches = (searched[:, :, None] - projected[:, None]).abs().amax(-1) < 1e-5  # [B, K - 1, K]
    assert matches.any(-1).all()


@pytest.mark.parametrize("method", METHODS)
def test_search_is_reproducible_under_the_actor_seed(method):
    obs = _observation()
    a, b = _actor(method)(obs.clone()), _actor(method)(obs.clone())
    assert (a == b).all()
    c = _actor(method, seed=4)(obs.clone())
    assert not torch.equal(a[keys.ACTION_CHUNK], c[keys.ACTION_CHUNK])
    assert torch.equal(a[CHOSEN_CANDIDATE], a[CANDIDATE_SCORES].argmax(-1))
    assert (a[CANDIDATE_SCORES].gather(-1, a[CHOSEN_CANDIDATE][:, None]) >= a[CANDIDATE_SCORES][:, :1]).all()


def test_gradient_ascent_through_the_scorer_ensemble():
    policy, encoder, world_model, scorer = _parts()
    actor = RerankingActor(
        policy,
        encoder,
        world_model,
        scorer,
        ensemble=ScorerEnsemble(encoder.latent_dim, hidden=32, members=3),
        num_candidates=6,
        candidates=CleanObservation(),
        search=SearchConfig("gradient", iterations=4),
        selection=SelectionConfig("argmax", "ensemble"),
        seed=3,
    )
    obs = _observation()
    cloud, agent_pos = obs[keys.POINT_CLOUD], obs[keys.AGENT_POS]
    executed = policy.config.executed
    seeds, candidates = _seeds(actor, cloud, agent_pos), actor.sample_candidates(cloud, agent_pos)
    objective = actor.objective(cloud, agent_pos)
    before, after = objective(seeds[:, :, executed]), objective(candidates[:, :, executed])
    assert torch.isfinite(after).all() and (after[:, 1:] > before[:, 1:]).any()
    torch.testing.assert_close(actor.score(cloud, agent_pos, candidates), after)


def test_search_settings_are_checked():
    with pytest.raises(ValueError, match="search method must be one of"):
        SearchConfig("annealing")
    with pytest.raises(ValueError, match="noise_std"):
        SearchConfig("shooting", noise_std=0)
    with pytest.raises(ValueError, match="lower elites"):
        _actor("cem", num_candidates=4, elites=4)
    with pytest.raises(ValueError, match="num_candidates >= 2"):
        _actor("mppi", num_candidates=1)
    with pytest.raises(ValueError, match=r"fixed_dims \[4\]"):
        _actor("gradient", fixed_dims=[4])
    assert SearchConfig().name == "none" and _actor("none").search.method == "none"
    assert SearchConfig("mppi", fixed_dims=[3]).name == "mppi(iterations=3, std=0.1, T=0.01, fixed=[3])"


def test_table2_script_evaluates_every_source_on_the_same_episodes(tmp_path, monkeypatch):
    """The script's wiring and outputs, with a stand-in for the evaluation (no simulator)."""
    import json
    import runpy
    import sys
    from pathlib import Path
    from types import SimpleNamespace

    import torchrl_dalir.checkpoints as checkpoints
    import torchrl_dalir.evaluation.compare as compare
    from torchrl_dalir.reranking import GaussianObservationNoise, PointDropout

    calls = []

    def fake_evaluate(policy_path, world_model_path, *, methods, candidates=None, search=None, **kwargs):
        calls.append({"policy": policy_path, "methods": methods, "candidates": candidates, "search": search, **kwargs})
        rate = {"stick-pull.pt": 0.5, "reach.pt": 0.25}[Path(policy_path).name] + 0.05 * (len(calls) % 4)
        name = compare.BASE if methods == ["base"] else compare.DALIR
        records = [{"success": (len(calls) + e) % 2 == 0} for e in range(kwargs["episodes"])]  # alternate by call
        return {name: {"success_rate": rate, "episodes": kwargs["episodes"], "seconds": 0.0, "records": records}}

    monkeypatch.setattr(compare, "evaluate_checkpoints", fake_evaluate)
    monkeypatch.setattr(checkpoints, "load_policy", lambda path, device: SimpleNamespace(task=Path(path).stem))
    script = Path(__file__).resolve().parents[1] / "examples" / "paper" / "table2_candidates.py"
    args = [
        "policies=[stick-pull.pt,reach.pt]",
        "world_models=[a.pt,b.pt]",
        "search.iterations=2",
        "episodes=3",
        f"out={tmp_path}",
    ]
    monkeypatch.setattr(sys, "argv", ["x", *args])
    runpy.run_path(str(script), run_name="__main__")
    assert len(calls) == 2 * 7 and {c["episodes"] for c in calls} == {3} and {c["seed"] for c in calls} == {0}
    by_source = calls[1:7]  # stick-pull: base, then dropout, noise, shooting, cem, mppi, gradient
    assert isinstance(by_source[0]["candidates"], PointDropout) and isinstance(
        by_source[1]["candidates"], GaussianObservationNoise
    )
    assert [c["search"].method for c in by_source[2:]] == ["shooting", "cem", "mppi", "gradient"]
    assert all(isinstance(c["candidates"], CleanObservation) and c["search"].iterations == 2 for c in by_source[2:])
    assert all(c["search"].fixed_dims == [3] for c in by_source[2:])  # MetaWorld: the gripper stays as sampled
    data = json.loads((tmp_path / "table2.json").read_text())
    assert [row["task"] for row in data["table"]] == ["stick-pull", "reach"]
    assert data["runs"][0]["methods"]["cem"]["search"].startswith("cem(iterations=2")
    assert (
        data["runs"][0]["methods"]["base"]["outcomes"] == "010"
        and data["runs"][0]["methods"]["dropout"]["outcomes"] == "101"
    )
    text = (tmp_path / "table2.md").read_text()
    assert "| point dropout | policy input |" in text and "| CEM | action chunk |" in text
    # paired with the base policy on the same episodes: base (call 1) solved episode 1,
    # dropout (call 2) episodes 0 and 2
    assert data["table"][0]["vs_base"]["dropout"] == {"base_only": 1, "dalir_only": 2, "p_value": 1.0}
    assert data["table"][0]["vs_base"]["noise"] == {"base_only": 0, "dalir_only": 0, "p_value": 1.0}
    assert "| 60.0 (1 / 2, p = 1.000) |" in text
    assert (tmp_path / "table2.png").stat().st_size > 0
    before = json.loads((tmp_path / "table2.json").read_text())
    (tmp_path / "parts" / "1_reach" / "cem.json").unlink()  # as if interrupted while measuring reach's CEM
    calls.clear()
    runpy.run_path(str(script), run_name="__main__")
    assert [(Path(c["policy"]).name, c["search"] and c["search"].method) for c in calls] == [("reach.pt", "cem")]
    assert json.loads((tmp_path / "table2.json").read_text())["runs"][0] == before["runs"][0]
    calls.clear()  # a changed setting measures again
    monkeypatch.setattr(sys, "argv", ["x", *args[:-1], "episodes=4", f"out={tmp_path}"])
    runpy.run_path(str(script), run_name="__main__")
    assert len(calls) == 2 * 7
    monkeypatch.setattr(sys, "argv", ["x", *args, "sources=[dropout,annealing]"])
    with pytest.raises(ValueError, match="unknown sources"):
        runpy.run_path(str(script), run_name="__main__")
