"""examples/paper/student_summary.py: the student's table is the committed result files' numbers, pooled per
backbone, a run whose screen failed has no test and counts 0 in Table 1."""

import json
import pathlib
import runpy
import shutil

import pytest

RESULTS = pathlib.Path(__file__).parents[1] / "docs" / "results"
SCRIPT = pathlib.Path(__file__).parents[1] / "examples" / "paper" / "student_summary.py"


def test_the_summary_holds_the_committed_numbers_and_pools_them(tmp_path):
    summary = runpy.run_path(str(SCRIPT))["main"]([f"out={tmp_path / 'summary'}"])
    rows = {row["run"]: row for row in summary["runs"]}
    stick_pull = rows["fm_stick_pull_s0"]
    assert (stick_pull["task"], stick_pull["seed"], stick_pull["split_decisions"]) == ("stick-pull", 0, 29)
    assert stick_pull["test"]["base"] == 0.08 and stick_pull["test"]["student"] == 0.26
    assert (stick_pull["test"]["won"], stick_pull["test"]["lost"]) == (20, 2)
    fm = [row["test"] for row in summary["runs"] if row["backbone"] == "fm" and row["test"]]
    assert summary["pooled"]["fm"]["dalir_only"] == sum(t["won"] for t in fm)
    assert summary["pooled"]["fm"]["base_only"] == sum(t["lost"] for t in fm)
    assert (
        "| fm_stick_pull_s0 | 29 | +5.2 ± 2.3 | 0.77 / +4.3 | 11 -> 22 % (15 / 4) | 8 -> 26 % (20 / 2"
        in (tmp_path / "summary.md").read_text()
    )
    gains = [t["student"] - t["base"] for t in fm]
    assert summary["pooled"]["fm"]["mean_gain"] == pytest.approx(sum(gains) / len(gains))
    # Table 1's mean: DP pen s0's screen failed (2 won / 6 lost), so it counts as gain 0 beside the tested runs
    pen = rows["dp_pen_s0"]
    assert not pen["passed"] and pen["test"] is None
    dp = [
        row["test"]["student"] - row["test"]["base"]
        for row in summary["runs"]
        if row["backbone"] == "dp" and row["test"]
    ]
    cells = {(cell["backbone"], cell["task"]): cell for cell in summary["per_task"]}
    dp_cells = [cell["mean_gain"] for (backbone, _), cell in cells.items() if backbone == "dp"]
    assert summary["pooled"]["dp"]["table1_runs"] == len(dp) + 1 == summary["pooled"]["dp"]["table1_tasks"]
    assert summary["pooled"]["dp"]["table1_gain"] == pytest.approx(sum(dp_cells) / len(dp_cells))
    fm_cells = [cell["mean_gain"] for (backbone, _), cell in cells.items() if backbone == "fm"]
    assert summary["pooled"]["fm"]["table1_gain"] == pytest.approx(sum(fm_cells) / len(fm_cells))  # over tasks
    assert cells[("dp", "pen")]["mean_gain"] == 0.0 and cells[("fm", "stick-pull")]["mean_gain"] == pytest.approx(
        (0.18 + 0.18 + 0.02) / 3
    )
    assert "| FM | stick-pull | 0, 1, 2 | +12.7 | +12.7 | +8.2 | +7.9 |" in (tmp_path / "summary.md").read_text()
    # beside the test gain, the same means of the honest ceiling and of the student's offline gain
    stick_pulls = [rows[f"fm_stick_pull_s{seed}"] for seed in range(3)]
    assert cells[("fm", "stick-pull")]["mean_ceiling"] == pytest.approx(sum(r["honest_gain"] for r in stick_pulls) / 3)
    assert cells[("fm", "stick-pull")]["mean_offline"] == pytest.approx(sum(r["student_gain"] for r in stick_pulls) / 3)
    fm_ceilings = [cell["mean_ceiling"] for (backbone, _), cell in cells.items() if backbone == "fm"]
    assert summary["pooled"]["fm"]["table1_ceiling"] == pytest.approx(sum(fm_ceilings) / len(fm_ceilings))
    assert json.loads((tmp_path / "summary.json").read_text())["pooled"] == summary["pooled"]
    assert (tmp_path / "summary.png").stat().st_size > 0


def test_a_passed_screen_without_its_test_is_pending_and_a_screen_needs_its_ladder(tmp_path):
    for name in ("scorer_benchmark_fm_stick_pull_s0.json", "student_screen_fm_stick_pull_s0.json"):
        shutil.copy(RESULTS / name, tmp_path / name)
    main = runpy.run_path(str(SCRIPT))["main"]
    summary = main([f"results={tmp_path}", f"out={tmp_path / 'summary'}"])
    assert summary["runs"][0]["passed"] and summary["runs"][0]["test"] is None
    assert summary["pooled"] == {} and summary["per_task"] == []  # pending: in no mean
    assert "not run yet" in (tmp_path / "summary.md").read_text()
    (tmp_path / "scorer_benchmark_fm_stick_pull_s0.json").unlink()
    with pytest.raises(FileNotFoundError, match="no ladder"):
        main([f"results={tmp_path}", f"out={tmp_path / 'summary'}"])


def test_the_gate_keeps_the_base_policy_where_the_offline_gain_is_small(tmp_path):
    main = runpy.run_path(str(SCRIPT))["main"]
    summary = main([f"out={tmp_path / 'summary'}"])
    rows = {row["run"]: row for row in summary["runs"]}
    # FM door s2: offline +0.7 points, below +2: the base policy runs, so its -12-point test counts 0 gated
    assert not rows["fm_door_s2"]["deployed"] and rows["fm_stick_pull_s0"]["deployed"]
    cells = {(cell["backbone"], cell["task"]): cell for cell in summary["per_task"]}
    assert cells[("fm", "door")]["mean_gain"] == pytest.approx((0.06 + 0.0 - 0.12) / 3)
    assert cells[("fm", "door")]["mean_gain_gated"] == 0.0
    assert cells[("fm", "stick-pull")]["mean_gain_gated"] == pytest.approx((0.18 + 0.18 + 0.02) / 3)
    fm = summary["pooled"]["fm"]
    fm_cells = [cell["mean_gain_gated"] for (backbone, _), cell in cells.items() if backbone == "fm"]
    assert fm["table1_gain_gated"] == pytest.approx(sum(fm_cells) / len(fm_cells))
    deployed = [row["test"] for row in summary["runs"] if row["backbone"] == "fm" and row["deployed"] and row["test"]]
    assert fm["deployed"]["runs"] == len(deployed) and fm["deployed"]["dalir_only"] == sum(t["won"] for t in deployed)
    # the runs the gate was chosen on are no evidence for it: with every run listed as seen, none is judged
    assert not rows["fm_stick_pull_s0"]["gate_judged"] and "| student (seen) |" in (tmp_path / "summary.md").read_text()
    everything = main([f"out={tmp_path / 'seen'}", f"gate_seen=[{','.join(rows)}]"])
    assert everything["pooled_gate_judged"] == {} and everything["pooled"] == summary["pooled"]
    judged = main([f"out={tmp_path / 'judged'}", "gate_seen=[]", "gate=0.05"])
    assert judged["pooled_gate_judged"] == judged["pooled"]
    stick_pull = next(cell for cell in judged["per_task"] if cell["task"] == "stick-pull")
    # s0's +4.3 offline is below a +5-point gate, s1's +11.8 and s2's +7.7 are not: s0 counts 0
    assert stick_pull["mean_gain_gated"] == pytest.approx((0.0 + 0.18 + 0.02) / 3)
