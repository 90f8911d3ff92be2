"""examples/paired_comparison.py: two methods on the same test episodes of named runs."""

import json
import runpy
from pathlib import Path

import pytest

from torchrl_dalir.pipeline.records import save_records

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "paired_comparison.py"


def record(task, seed, methods):
    return {"version": 1, "task": task, "policy": "dp", "seed": seed, "variant": "frozen+explore", "run": f"run{seed}",
            "eval_seed": 0, "episodes": 4, "num_candidates": 32, "command": "", "commit": None, "methods": methods}


@pytest.fixture
def script():
    return runpy.run_path(str(SCRIPT))


def test_counts_each_run_and_pools_them_with_the_two_sided_sign_test(tmp_path, script):
    save_records([
        record("stick-pull", 1, {"base": {"success_rate": 0.5, "outcomes": "1100"}, "random": {"success_rate": 0.75, "outcomes": "0111"}}),
        record("stick-pull", 2, {"base": {"success_rate": 0.25, "outcomes": "1000"}, "random": {"success_rate": 0.75, "outcomes": "0111"}}),
        record("shelf-place", 1, {"base": {"success_rate": 0.0, "outcomes": "0000"}, "random": {"success_rate": 1.0, "outcomes": "1111"}}),
    ], tmp_path / "runs")
    cfg = script["Config"](runs=["dp/stick-pull/1", "dp/stick-pull/2"], records=[str(tmp_path / "runs")], variant="frozen+explore",
                           json=str(tmp_path / "out.json"))
    result = script["compare"](cfg)  # shelf-place is not named: not read
    # s1: 1100 vs 0111 -> only base 1, only random 2; s2: 1000 vs 0111 -> 1 / 3; pooled 2 / 5, p = 2 * P(X <= 2 | 7) = 29 / 64
    assert [(r["against_only"], r["method_only"], r["net"]) for r in result["runs"]] == [(1, 2, 1), (1, 3, 2)]
    assert result["pooled"] == {"against_only": 2, "method_only": 5, "p_two_sided": pytest.approx(29 / 64)}
    assert result["largest_net_loss"] == 0
    assert "| pooled | | | | 2 / 5 (two-sided p = 0.453) |" in script["markdown"](result)
    with pytest.raises(ValueError, match="no frozen\\+explore record of run dp/pick-place-wall/1"):
        script["compare"](script["Config"](runs=["dp/pick-place-wall/1"], records=[str(tmp_path / "runs")], variant="frozen+explore"))
    with pytest.raises(ValueError, match="has no \\['argmax'\\]"):
        script["compare"](script["Config"](runs=["dp/stick-pull/1"], method="argmax", records=[str(tmp_path / "runs")], variant="frozen+explore"))


def test_adds_an_evaluation_of_the_records_test_episodes_and_refuses_other_episodes(tmp_path, script):
    save_records([record("stick-pull", 2, {"base": {"success_rate": 0.5, "outcomes": "1100"}})], tmp_path / "runs")
    episodes = [{"success": s} for s in (False, False, True, True)]
    evaluation = {"config": {"seed": 0, "episodes": 4}, "success": {"point-dropout policy": {"success_rate": 0.5, "records": episodes}}}
    (tmp_path / "evaluation.json").write_text(json.dumps(evaluation))
    kwargs = dict(runs=["dp/stick-pull/2"], method="dropout", records=[str(tmp_path / "runs")], variant="frozen+explore",
                  evaluations=[str(tmp_path / "evaluation.json")])
    result = script["compare"](script["Config"](**kwargs))
    assert result["runs"][0]["against_only"] == 2 and result["runs"][0]["method_only"] == 2 and result["largest_net_loss"] == 0
    (tmp_path / "evaluation.json").write_text(json.dumps({**evaluation, "config": {"seed": 1, "episodes": 4}}))
    with pytest.raises(ValueError, match="not the record's 4 of seed 0"):
        script["compare"](script["Config"](**kwargs))
    with pytest.raises(ValueError, match="give one per run"):
        script["Config"](**{**kwargs, "evaluations": ["a", "b"]})
    with pytest.raises(ValueError, match="unknown methods"):
        script["Config"](runs=["dp/stick-pull/2"], method="oracle")
