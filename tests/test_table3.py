"""Paper Table 3's command: its runs' settings and its tables, on hand-made results (no simulator)."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from torchrl_dalir.config import parse_config
from torchrl_dalir.evaluation.compare import ARGMAX, BASE
from torchrl_dalir.pipeline import PRESETS, PipelineConfig

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "paper" / "table3_diagnostics.py"


@pytest.fixture
def table3(monkeypatch):
    """The script as a module (its ``main`` not run), so that a test can replace its ``run``."""
    spec = importlib.util.spec_from_file_location("table3_diagnostics", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def fake_runs(outcomes):
    """In place of the main-job processes: ``outcomes[(task, seed, variant)]`` gives the success of
    the base policy and of arg-max, and the world model's held-out MSE."""

    def run(_, task, seed, variant):
        base, argmax, mse = outcomes[(task, seed, variant)]
        return {
            "task": task,
            "seed": seed,
            "variant": variant,
            "command": [],
            "episodes": 50,
            "success": {BASE: base, ARGMAX: argmax},
            "metrics": {"wm_mse": mse, "no_change_mse": 0.01},
        }

    return run


def test_every_variant_is_its_own_main_job_run_evaluated_by_argmax_alone(table3):
    cfg = parse_config(
        table3.Config, ["part=b", "mixed_sizes=[100,0]", "overrides=[world_model.encoder=finetune]", "out=/tmp/t3"]
    )
    assert cfg.tasks == ["disassemble"]
    assert list(table3.variants(cfg)) == ["", "mixed100"]
    names = {}
    for variant in ("", "mixed100"):
        arguments = table3.run_arguments(cfg, "disassemble", 1, variant)
        pipeline = parse_config(PipelineConfig, arguments, PRESETS)
        names[variant] = pipeline.run_name()
        assert pipeline.world_model.encoder == "finetune"  # the override, over the cpu preset's frozen
        assert pipeline.eval_methods == (["argmax"] if variant else ["base", "dalir", "argmax", "random"])
        assert pipeline.calibration_episodes == (0 if variant else 30)
    assert names == {"": "fm_seed1+explore_fm_seed1", "mixed100": "fm_seed1_mixed100+explore_fm_seed1"}
    part_a = parse_config(table3.Config, ["part=a"])
    assert part_a.tasks == ["pen", "disassemble"]
    assert "world_model.scorer_target=dense_reward" in table3.run_arguments(part_a, "pen", 0, "dense_reward")
    with pytest.raises(ValueError, match="part"):
        parse_config(table3.Config, ["part=c"])
    with pytest.raises(ValueError, match="mixed_sizes"):
        parse_config(table3.Config, ["part=b", "mixed_sizes=[-5]"])


def test_table_a_puts_base_sparse_and_dense_side_by_side(table3, tmp_path, monkeypatch):
    outcomes = {
        ("pen", 0, ""): (0.40, 0.46, 0),
        ("pen", 0, "dense_reward"): (0.40, 0.50, 0),
        ("disassemble", 0, ""): (0.80, 0.84, 0),
        ("disassemble", 0, "dense_reward"): (0.80, 0.90, 0),
    }
    monkeypatch.setattr(table3, "run", fake_runs(outcomes))
    table3.main([f"table_out={tmp_path}"])
    data = json.loads((tmp_path / "table3a.json").read_text())
    assert data["table"] == [
        {"task": "pen", "base": [0.40], "sparse": [0.46], "dense": [0.50]},
        {"task": "disassemble", "base": [0.80], "sparse": [0.84], "dense": [0.90]},
    ]
    text = (tmp_path / "table3a.md").read_text()
    assert "| sparse terminal labels | 46.0 | 84.0 | 65.0 |" in text
    assert "| dense simulator reward (oracle) | 50.0 | 90.0 | 70.0 |" in text
    assert (tmp_path / "table3a.png").stat().st_size > 0


def test_table_b_reports_mse_and_success_per_data_size_mean_over_seeds(table3, tmp_path, monkeypatch):
    outcomes = {
        ("disassemble", s, v): (0.8 if not v else None, rate, mse)
        for s, v, rate, mse in [  # (a variant runs no base policy)
            (0, "", 0.86, 0.0010),
            (1, "", 0.84, 0.0012),
            (0, "mixed100", 0.80, 0.0030),
            (1, "mixed100", 0.78, 0.0034),
        ]
    }
    monkeypatch.setattr(table3, "run", fake_runs(outcomes))
    table3.main(["part=b", "seeds=[0,1]", "mixed_sizes=[100,0]", f"table_out={tmp_path}"])
    rows = json.loads((tmp_path / "table3b.json").read_text())["table"]
    assert [(r["mixed_trajectories"], r["success"], r["wm_mse"]) for r in rows] == [
        (100, [0.80, 0.78], [0.0030, 0.0034]),
        ("all", [0.86, 0.84], [0.0010, 0.0012]),
    ]
    text = (tmp_path / "table3b.md").read_text()
    assert all(r["base"] == [0.8, 0.8] for r in rows)  # the main runs' base policy, for every size
    assert (
        "| disassemble | 100 | 0.00320 | 0.01000 | 80.0 | 79.0 |" in text
        and "| disassemble | all | 0.00110 | 0.01000 | 80.0 | 85.0 |" in text
    )
    assert (tmp_path / "table3b.png").stat().st_size > 0
