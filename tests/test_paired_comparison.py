"""examples/paper/paired_comparison.py: two methods on the same test episodes of named runs."""

import json
import runpy
from pathlib import Path

import pytest

from torchrl_dalir.pipeline.records import save_records

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "paper" / "paired_comparison.py"


def record(task, seed, methods):
    return {
        "version": 1,
        "task": task,
        "policy": "dp",
        "seed": seed,
        "variant": "frozen+explore",
        "run": f"run{seed}",
        "eval_seed": 0,
        "episodes": 4,
        "num_candidates": 32,
        "command": "",
        "commit": None,
        "methods": methods,
    }


@pytest.fixture
def script():
    return runpy.run_path(str(SCRIPT))


def test_counts_each_run_and_pools_them_with_the_two_sided_sign_test(tmp_path, script):
    save_records(
        [
            record(
                "stick-pull",
                1,
                {
                    "base": {"success_rate": 0.5, "outcomes": "1100"},
                    "random": {"success_rate": 0.75, "outcomes": "0111"},
                },
            ),
            record(
                "stick-pull",
                2,
                {
                    "base": {"success_rate": 0.25, "outcomes": "1000"},
                    "random": {"success_rate": 0.75, "outcomes": "0111"},
                },
            ),
            record(
                "shelf-place",
                1,
                {
                    "base": {"success_rate": 0.0, "outcomes": "0000"},
                    "random": {"success_rate": 1.0, "outcomes": "1111"},
                },
            ),
        ],
        tmp_path / "runs",
    )
    cfg = script["Config"](
        runs=["dp/stick-pull/1", "dp/stick-pull/2"],
        records=[str(tmp_path / "runs")],
        variant="frozen+explore",
        json=str(tmp_path / "out.json"),
    )
    result = script["compare"](cfg)  # shelf-place is not named: not read
    # s1: 1100 vs 0111 -> only base 1, only random 2; s2: 1000 vs 0111 -> 1 / 3;
    # pooled 2 / 5, p = 2 * P(X <= 2 | 7) = 29 / 64
    assert [(r["against_only"], r["method_only"], r["net"]) for r in result["runs"]] == [(1, 2, 1), (1, 3, 2)]
    assert result["pooled"] == {"against_only": 2, "method_only": 5, "p_two_sided": pytest.approx(29 / 64)}
    assert result["largest_net_loss"] == 0
    assert "| pooled | | | | 2 / 5 (two-sided p = 0.453) |" in script["markdown"](result)
    with pytest.raises(ValueError, match="no frozen\\+explore record of run dp/pick-place-wall/1"):
        script["compare"](
            script["Config"](runs=["dp/pick-place-wall/1"], records=[str(tmp_path / "runs")], variant="frozen+explore")
        )
    with pytest.raises(ValueError, match="has no \\['argmax'\\]"):
        script["compare"](
            script["Config"](
                runs=["dp/stick-pull/1"], method="argmax", records=[str(tmp_path / "runs")], variant="frozen+explore"
            )
        )


def evaluation(task, run_seed, outcomes, name="point-dropout policy", **config):
    records = [{"success": c == "1"} for c in outcomes]
    checkpoint = f"/runs/{task}/policies/{task}/dp_seed{run_seed}/checkpoint.pt"
    return {
        "config": {
            "seed": 0,
            "episodes": len(outcomes),
            "policy_checkpoint": checkpoint,
            "actor_seed": run_seed,
            **config,
        },
        "success": {name: {"success_rate": outcomes.count("1") / len(outcomes), "records": records}},
    }


def test_adds_each_runs_evaluation_and_refuses_one_of_other_episodes_another_run_or_other_outcomes(tmp_path, script):
    save_records(
        [
            record(
                "stick-pull",
                2,
                {
                    "base": {"success_rate": 0.5, "outcomes": "1100"},
                    "random": {"success_rate": 0.5, "outcomes": "0101"},
                },
            ),
            record(
                "pick-place-wall",
                1,
                {
                    "base": {"success_rate": 0.25, "outcomes": "0001"},
                    "random": {"success_rate": 0.5, "outcomes": "1001"},
                },
            ),
        ],
        tmp_path / "runs",
    )
    paths = [tmp_path / "sp.json", tmp_path / "ppw.json"]
    paths[0].write_text(json.dumps(evaluation("stick-pull", 2, "0011")))
    paths[1].write_text(json.dumps(evaluation("pick-place-wall", 1, "1111")))
    kwargs = dict(
        runs=["dp/stick-pull/2", "dp/pick-place-wall/1"],
        method="dropout",
        against="random",
        records=[str(tmp_path / "runs")],
        variant="frozen+explore",
        evaluations=[str(p) for p in paths],
    )
    result = script["compare"](script["Config"](**kwargs))
    # against the random pick: 0101 vs 0011 -> 1 / 1; 1001 vs 1111 -> 0 / 2
    assert [(r["against_only"], r["method_only"]) for r in result["runs"]] == [(1, 1), (0, 2)]
    assert result["pooled"]["against_only"] == 1 and result["pooled"]["method_only"] == 3
    with pytest.raises(
        ValueError, match="not the policy of stick-pull dp seed 2"
    ):  # evaluations given in the wrong order
        script["compare"](script["Config"](**{**kwargs, "evaluations": kwargs["evaluations"][::-1]}))
    paths[0].write_text(json.dumps(evaluation("stick-pull", 2, "0011", actor_seed=0)))
    with pytest.raises(ValueError, match="actor_seed=0"):
        script["compare"](script["Config"](**kwargs))
    paths[0].write_text(json.dumps(evaluation("stick-pull", 2, "0011", seed=1)))
    with pytest.raises(ValueError, match="not the record's 4 of seed 0"):
        script["compare"](script["Config"](**kwargs))
    paths[0].write_text(
        json.dumps(evaluation("stick-pull", 2, "1110", name="base policy"))
    )  # the record's base is 1100
    with pytest.raises(ValueError, match="base's outcomes are not those of the record"):
        script["compare"](script["Config"](**{**kwargs, "method": "base"}))


def test_refuses_a_run_named_twice_one_method_against_itself_and_unknown_methods(script):
    with pytest.raises(ValueError, match="give one per run"):
        script["Config"](runs=["dp/stick-pull/2"], evaluations=["a", "b"])
    with pytest.raises(ValueError, match="name a run twice"):
        script["Config"](runs=["dp/stick-pull/2", "dp/stick-pull/2"])
    with pytest.raises(ValueError, match="compare two methods"):
        script["Config"](runs=["dp/stick-pull/2"], method="base")
    with pytest.raises(ValueError, match="unknown methods"):
        script["Config"](runs=["dp/stick-pull/2"], method="oracle")
