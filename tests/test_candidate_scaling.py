"""examples/paper/candidate_scaling.py: its wiring, pairing and resumption, with a stand-in for the evaluation."""

import json
import runpy
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from torchrl_dalir.reranking.selection import SelectionConfig

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "paper" / "candidate_scaling.py"
OUTCOMES = {
    ("base", 1): "0101",
    ("argmax", 4): "1101",
    ("argmax", 16): "1111",
    ("random", 4): "0100",
    ("random", 16): "0001",
    ("dalir", 4): "0111",
    ("dalir", 16): "0110",
}


@pytest.fixture
def fake_evaluation(monkeypatch):
    """``evaluate_checkpoints`` answering from ``OUTCOMES`` per (method, N), and a world model whose
    stored rule is ``stored["rule"]``; returns the calls (policy, method, N and every other argument) and ``stored``."""
    import torchrl_dalir.checkpoints as checkpoints
    import torchrl_dalir.evaluation.compare as compare

    calls, stored = [], {"rule": SelectionConfig("argmax", "ensemble")}

    def fake_evaluate(policy_path, world_model_path, *, methods, num_candidates, **kwargs):
        calls.append((Path(policy_path).name, methods[0], num_candidates, kwargs))
        results = OUTCOMES[methods[0], num_candidates]
        records = [{"success": c == "1"} for c in results]
        return {
            compare.METHODS[methods[0]]: {
                "success_rate": results.count("1") / len(results),
                "episodes": len(results),
                "seconds": 0.0,
                "records": records,
            }
        }

    monkeypatch.setattr(compare, "evaluate_checkpoints", fake_evaluate)
    monkeypatch.setattr(checkpoints, "load_policy", lambda path, device: SimpleNamespace(task="disassemble"))
    monkeypatch.setattr(checkpoints, "load_world_model", lambda path, policy: SimpleNamespace(selection=stored["rule"]))
    return calls, stored


def _run(monkeypatch, *args):
    monkeypatch.setattr(sys, "argv", ["x", *args])
    runpy.run_path(str(SCRIPT), run_name="__main__")


def test_every_method_at_every_count_on_the_same_episodes_paired_with_the_base_policy(
    tmp_path, monkeypatch, fake_evaluation
):
    calls, _ = fake_evaluation
    args = [
        "policies=[dp_seed0/p.pt]",
        "world_models=[w.pt]",
        "candidates=[16,4,4]",
        "methods=[argmax,random]",
        "episodes=4",
        "actor_seed=3",
        f"out={tmp_path}",
    ]
    _run(monkeypatch, *args)
    assert [c[1:3] for c in calls] == [
        ("base", 1),
        ("argmax", 4),
        ("argmax", 16),
        ("random", 4),
        ("random", 16),
    ]  # counts sorted, each once
    assert all(
        c[3] == {"episodes": 4, "seed": 0, "device": "cpu", "dropout": 0.2, "actor_seed": 3, "common_noise": True}
        for c in calls
    )
    data = json.loads((tmp_path / "candidate_scaling.json").read_text())
    argmax, random = data["table"]
    assert (
        argmax["run"] == "disassemble dp_seed0"
        and argmax["candidates"] == [1, 4, 16]
        and argmax["success"] == [0.5, 0.75, 1.0]
    )
    # base 0101: argmax at N=16 (1111) solved episodes 0 and 2 that the base policy failed;
    # random at N=4 (0100) lost episode 3
    assert argmax["vs_base"]["16"] == {"base_only": 0, "method_only": 2, "p_value": 0.5}
    assert random["vs_base"]["4"] == {"base_only": 1, "method_only": 0, "p_value": 1.0}
    assert data["runs"][0]["methods"]["argmax"]["4"]["outcomes"] == "1101"
    text = (tmp_path / "candidate_scaling.md").read_text()
    assert "| disassemble dp_seed0 | argmax | 50.0 | 75.0 (0 / 1, p = 1.00) | 100.0 (0 / 2, p = 0.50) |" in text
    assert (tmp_path / "candidate_scaling.png").stat().st_size > 0

    (tmp_path / "parts" / "0_disassemble" / "random_16.json").unlink()  # as if interrupted while measuring it
    calls.clear()
    _run(monkeypatch, *args)
    assert [c[1:3] for c in calls] == [("random", 16)]
    calls.clear()
    _run(
        monkeypatch, *args[:-1], "dropout=0.1", f"out={tmp_path}"
    )  # the candidates change, the base policy's episodes do not
    assert [c[1:3] for c in calls] == [("argmax", 4), ("argmax", 16), ("random", 4), ("random", 16)]


def test_the_calibrated_rule_replays_the_base_policy_or_shares_a_row_or_runs(tmp_path, monkeypatch, fake_evaluation):
    calls, stored = fake_evaluation
    args = [
        "policies=[a/p.pt,b/q.pt]",
        "world_models=[v.pt,w.pt]",
        "candidates=[4]",
        "methods=[dalir,argmax]",
        "episodes=4",
    ]
    stored["rule"] = SelectionConfig("margin", "ensemble", k=1.0, margin=1.0)  # a calibration that kept the base policy
    _run(monkeypatch, *args, f"out={tmp_path / 'kept'}")
    assert [c[:3] for c in calls] == [
        ("p.pt", "base", 1),
        ("p.pt", "argmax", 4),
        ("q.pt", "base", 1),
        ("q.pt", "argmax", 4),
    ]
    data = json.loads((tmp_path / "kept" / "candidate_scaling.json").read_text())
    assert data["runs"][0]["methods"]["dalir"]["4"]["replays"] == "base policy"
    assert [row["run"] for row in data["table"]] == ["disassemble a", "disassemble a", "disassemble b", "disassemble b"]
    assert data["table"][0]["success"] == [0.5, 0.5] and data["table"][0]["vs_base"]["4"]["method_only"] == 0

    calls.clear()
    stored["rule"] = SelectionConfig()  # never calibrated: the checkpoint's rule is the paper's arg-max, run once
    _run(
        monkeypatch,
        *args[:1],
        "world_models=[v.pt,w.pt]",
        "candidates=[4]",
        "methods=[dalir,argmax]",
        "episodes=4",
        f"out={tmp_path / 'argmax'}",
    )
    assert [c[:3] for c in calls] == [
        ("p.pt", "base", 1),
        ("p.pt", "dalir", 4),
        ("q.pt", "base", 1),
        ("q.pt", "dalir", 4),
    ]

    calls.clear()
    stored["rule"] = SelectionConfig("argmax", "ensemble")  # another rule: its own rows, not the old ones
    _run(monkeypatch, *args, f"out={tmp_path / 'argmax'}")
    assert [c[:3] for c in calls] == [
        ("p.pt", "dalir", 4),
        ("p.pt", "argmax", 4),
        ("q.pt", "dalir", 4),
        ("q.pt", "argmax", 4),
    ]


@pytest.mark.parametrize(
    "bad, message",
    [
        ("methods=[best]", "methods"),
        ("candidates=[1,4]", "N = 1 is the base policy"),
        ("dropout=1.5", "dropout"),
        ("world_models=[w.pt,v.pt]", "1 policies but 2 world models"),
    ],
)
def test_bad_settings_are_refused_before_any_episode(bad, message, tmp_path, monkeypatch, fake_evaluation):
    calls, _ = fake_evaluation
    with pytest.raises(ValueError, match=message):
        _run(monkeypatch, "policies=[p.pt]", "world_models=[w.pt]", bad, f"out={tmp_path}")
    assert calls == []
