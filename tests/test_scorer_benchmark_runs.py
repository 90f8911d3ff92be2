"""examples/paper/scorer_benchmark_runs.py: each run's five stages in order, done stages skipped, a failure stops
the run and not the others (every stage's process is stubbed: the real ones take an hour)."""

import json
import pathlib
import runpy

import pytest

SCRIPT = pathlib.Path(__file__).parents[1] / "examples" / "paper" / "scorer_benchmark_runs.py"


@pytest.fixture
def script(monkeypatch):
    module = runpy.run_path(str(SCRIPT))
    calls = []

    def fake_run_logged(command, log, threads):
        """A stage's process: writes the artifact its command names, except the stick-pull redraws, which fail."""
        calls.append(command)
        stage = {"build=": "benchmark", "distill=": "distillation", "json=": "redraws"}
        artifact = next((a.split("=", 1)[1] for a in command for k in stage if a.startswith(k)), None)
        if "outcome_noise.py" in command[1] and "stick-pull" in " ".join(command):
            return 1, 0.5
        if "train_dp3_wm.py" in command[1]:
            out = next(a[4:] for a in command if a.startswith("out="))
            task = next(a[5:] for a in command if a.startswith("task="))
            artifact = f"{out}/policies/{task}/fm_seed0/checkpoint.pt"
        if "branched_ranking.py" in command[1]:
            policy = pathlib.Path(next(a[7:] for a in command if a.startswith("policy=")))
            out = next(a[4:] for a in command if a.startswith("out="))
            artifact = f"{out}/{policy.parent.parent.name}/{policy.parent.name}/dropout/rows"
        pathlib.Path(artifact).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(artifact).touch()
        return 0, 1.0

    monkeypatch.setitem(module["run_one"].__globals__, "run_logged", fake_run_logged)
    return module, calls


def test_the_stages_run_in_order_resume_and_stop_at_a_failure(script, tmp_path):
    module, calls = script
    argv = [f"out={tmp_path / 'out'}", f"results={tmp_path}", "tasks=[disassemble,stick-pull]", "jobs=1"]
    with pytest.raises(SystemExit, match="1 of 2 runs failed"):
        module["main"](argv)
    scripts = [pathlib.Path(c[1]).name for c in calls]
    chain = ["train_dp3_wm.py", "branched_ranking.py", "outcome_noise.py", "scorer_benchmark.py", "scorer_benchmark.py"]
    assert scripts == chain + chain[:3]  # stick-pull stops at its failed redraws
    assert (tmp_path / "benchmarks" / "scorer" / "distill" / "fm_disassemble_s0.pt").exists()
    assert "draws=[1,2,3]" in calls[2] and "only_split=false" in calls[2]
    summary = json.loads((tmp_path / "out" / "scorer_benchmark_runs.json").read_text())
    assert [r.get("failed") for r in summary["runs"]] == [None, "redraws"]

    calls.clear()  # resumed: only what was not done runs again
    with pytest.raises(SystemExit):
        module["main"](argv)
    assert [pathlib.Path(c[1]).name for c in calls] == ["outcome_noise.py"]
    summary = json.loads((tmp_path / "out" / "scorer_benchmark_runs.json").read_text())
    assert summary["runs"][0]["stages"] == dict.fromkeys(
        ["policy", "branching", "redraws", "benchmark", "distillation"], "done before"
    )


def test_an_unknown_task_or_backbone_and_a_single_candidate_are_refused(script):
    module, _ = script
    with pytest.raises(ValueError, match="task"):
        module["main"](["tasks=[drawer-open-typo]"])
    with pytest.raises(ValueError, match="policy"):
        module["main"](["policy=ppo"])
    with pytest.raises(ValueError, match="num_candidates must be at least 2, got 1"):
        module["main"](["num_candidates=1"])
