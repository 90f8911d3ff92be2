"""examples/candidate_scaling.py: its wiring, pairing and resumption, with a stand-in for the evaluation."""

import json
import runpy
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "candidate_scaling.py"


@pytest.fixture
def fake_evaluation(monkeypatch):
    """``evaluate_checkpoints`` answering from a table of outcomes per (method, N); the calls it got."""
    import torchrl_dalir.checkpoints as checkpoints
    import torchrl_dalir.evaluation.compare as compare

    outcomes = {("base", 1): "0101", ("argmax", 4): "1101", ("argmax", 16): "1111", ("random", 4): "0100", ("random", 16): "0001"}
    calls = []

    def fake_evaluate(policy_path, world_model_path, *, methods, num_candidates, **kwargs):
        calls.append((methods, num_candidates, kwargs["episodes"], kwargs["seed"], kwargs["dropout"]))
        results = outcomes[methods[0], num_candidates]
        records = [{"success": c == "1"} for c in results]
        return {compare.METHODS[methods[0]]: {"success_rate": results.count("1") / len(results), "episodes": len(results),
                                              "seconds": 0.0, "records": records}}

    monkeypatch.setattr(compare, "evaluate_checkpoints", fake_evaluate)
    monkeypatch.setattr(checkpoints, "load_policy", lambda path, device: SimpleNamespace(task="disassemble", config=SimpleNamespace(kind="dp")))
    return calls


def _run(monkeypatch, *args):
    monkeypatch.setattr(sys, "argv", ["x", *args])
    runpy.run_path(str(SCRIPT), run_name="__main__")


def test_every_method_at_every_count_on_the_same_episodes_paired_with_the_base_policy(tmp_path, monkeypatch, fake_evaluation):
    args = ["policies=[p.pt]", "world_models=[w.pt]", "candidates=[16,4,4]", "methods=[argmax,random]", "episodes=4", f"out={tmp_path}"]
    _run(monkeypatch, *args)
    assert fake_evaluation == [(["base"], 1, 4, 0, 0.2), (["argmax"], 4, 4, 0, 0.2), (["argmax"], 16, 4, 0, 0.2),
                               (["random"], 4, 4, 0, 0.2), (["random"], 16, 4, 0, 0.2)]  # counts sorted, each once
    data = json.loads((tmp_path / "candidate_scaling.json").read_text())
    argmax, random = data["table"]
    assert argmax["candidates"] == [1, 4, 16] and argmax["success"] == [0.5, 0.75, 1.0]
    # base 0101: argmax at N=16 (1111) solved episodes 0 and 2 that the base policy failed; random at N=4 (0100) lost episode 3
    assert argmax["vs_base"]["16"] == {"base_only": 0, "dalir_only": 2, "p_value": 0.5}
    assert random["vs_base"]["4"] == {"base_only": 1, "dalir_only": 0, "p_value": 1.0}
    assert data["runs"][0]["methods"]["argmax"]["4"]["outcomes"] == "1101"
    text = (tmp_path / "candidate_scaling.md").read_text()
    assert "| disassemble dp | argmax | 50.0 | 75.0 (0 / 1, p = 1.00) | 100.0 (0 / 2, p = 0.50) |" in text
    assert (tmp_path / "candidate_scaling.png").stat().st_size > 0

    (tmp_path / "parts" / "0_disassemble" / "random_16.json").unlink()  # as if interrupted while measuring it
    fake_evaluation.clear()
    _run(monkeypatch, *args)
    assert fake_evaluation == [(["random"], 16, 4, 0, 0.2)]
    _run(monkeypatch, *args[:-2], "episodes=4", "dropout=0.1", f"out={tmp_path}")  # other inputs: measured anew
    assert len(fake_evaluation) == 1 + 5


@pytest.mark.parametrize("bad, message", [
    ("methods=[best]", "methods must be among"),
    ("candidates=[1,4]", "candidates"),
    ("world_models=[w.pt,v.pt]", "1 policies but 2 world models"),
])
def test_bad_settings_are_refused_before_any_episode(bad, message, tmp_path, monkeypatch, fake_evaluation):
    with pytest.raises(ValueError, match=message):
        _run(monkeypatch, "policies=[p.pt]", "world_models=[w.pt]", bad, f"out={tmp_path}")
    assert fake_evaluation == []
