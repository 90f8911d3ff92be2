"""examples/paper/scorer_benchmark_runs.py: each run's five stages in order, every command accepted by its
script's own configuration, done stages skipped, a failure stops its run and not the others (every stage's
process is stubbed: the real ones take an hour)."""

import json
import pathlib
import runpy

import pytest
import torch

from torchrl_dalir.config import parse_config
from torchrl_dalir.pipeline import PRESETS, PipelineConfig

EXAMPLES = pathlib.Path(__file__).parents[1] / "examples"
SCRIPT = EXAMPLES / "paper" / "scorer_benchmark_runs.py"
STAGES = ["policy", "branching", "redraws", "benchmark", "distillation"]


def _stage(command: list[str]) -> tuple[str, pathlib.Path]:
    """The stage ``command`` runs, parsed by its script's ``Config``, and where that script writes its artifact."""
    script, argv = pathlib.Path(command[1]), command[2:]
    if script.name == "train_dp3_wm.py":
        cfg = parse_config(PipelineConfig, argv, PRESETS)
        return "policy", cfg.policy_training.run_dir() / "checkpoint.pt"
    cfg = parse_config(runpy.run_path(str(script))["Config"], argv)
    if script.name == "branched_ranking.py":  # collect_branched's folder: <out>/<task>/<policy's run>/<generator>
        policy = pathlib.Path(cfg.policy)
        return "branching", pathlib.Path(cfg.out) / policy.parents[1].name / policy.parent.name / cfg.generator
    if script.name == "outcome_noise.py":
        assert (cfg.draws, cfg.only_split) == ([1, 2, 3], False)  # the honest ceiling's redraws
        return "redraws", pathlib.Path(cfg.json)
    if script.name == "critic_screen.py":
        assert cfg.student and cfg.episodes == 100 and cfg.seed == (0 if cfg.test else 1) and cfg.decisions == 1
        return ("test" if cfg.test else "screen"), pathlib.Path(cfg.json)
    if cfg.files:  # scorer_benchmark.py measuring the ladder on the run's benchmark file
        return "ladder", pathlib.Path(cfg.json)
    return ("benchmark", pathlib.Path(cfg.build)) if cfg.build else ("distillation", pathlib.Path(cfg.distill))


@pytest.fixture
def script(monkeypatch):
    module = runpy.run_path(str(SCRIPT))
    calls = []

    def fake_run_logged(command, log, threads):
        """A stage's process: writes its artifact, except the stick-pull redraws, which fail."""
        stage, artifact = _stage(command)
        calls.append(stage)
        if stage == "redraws" and "stick_pull" in artifact.name:
            return 1, 0.5
        artifact.parent.mkdir(parents=True, exist_ok=True)
        if stage == "policy":
            torch.save({"step": 10, "num_steps": 10}, artifact)
        elif stage == "branching":
            artifact.mkdir()
            (artifact / "meta.json").write_text(json.dumps({"complete": True}))
        elif stage == "screen":  # disassemble's student wins 5 and loses 3 of its episodes, shelf-place's 3 and 3
            won = 5 if "disassemble" in artifact.name else 3
            artifact.write_text(json.dumps({"paired": {"dalir_only": won, "base_only": 3}}))
        else:
            artifact.touch()
        return 0, 1.0

    monkeypatch.setitem(module["run_one"].__globals__, "run_logged", fake_run_logged)
    return module, calls


def test_the_stages_run_in_order_resume_and_stop_at_a_failure(script, tmp_path):
    module, calls = script
    argv = [f"out={tmp_path}", "tasks=[disassemble,stick-pull]", "jobs=1"]
    with pytest.raises(SystemExit, match="1 of 2 runs failed"):
        module["main"](argv)
    assert calls == STAGES + STAGES[:3]  # stick-pull stops at its failed redraws
    assert (tmp_path / "benchmarks" / "scorer" / "distill" / "fm_disassemble_s0.pt").exists()
    summary = json.loads((tmp_path / "scorer_benchmark_runs.json").read_text())
    assert [r.get("failed") for r in summary["runs"]] == [None, "redraws"]

    calls.clear()  # resumed: only what was not done runs again
    with pytest.raises(SystemExit):
        module["main"](argv)
    assert calls == ["redraws"]
    summary = json.loads((tmp_path / "scorer_benchmark_runs.json").read_text())
    assert summary["runs"][0]["stages"] == dict.fromkeys(STAGES, "done before")


def test_an_interrupted_policy_or_branching_is_not_done(script, tmp_path):
    """A checkpoint short of its last step, or branched rows without a complete meta.json, run again."""
    module, calls = script
    argv = [f"out={tmp_path}", "tasks=[disassemble]"]
    module["main"](argv)
    ((_, policy_done, _), (_, branching_done, _), *_) = module["stages"](
        module["Config"](out=str(tmp_path)), "disassemble", 0
    )
    policy = tmp_path / "policies" / "disassemble" / "fm_seed0" / "checkpoint.pt"
    torch.save({"step": 5, "num_steps": 10}, policy)
    meta = tmp_path / "branched" / "disassemble" / "fm_seed0" / "dropout" / "meta.json"
    meta.write_text(json.dumps({"complete": False}))
    assert not policy_done() and not branching_done()


def test_an_unknown_task_or_backbone_and_a_single_candidate_are_refused(script):
    module, _ = script
    with pytest.raises(ValueError, match="task"):
        module["main"](["tasks=[drawer-open-typo]"])
    with pytest.raises(ValueError, match="policy"):
        module["main"](["policy=ppo"])
    with pytest.raises(ValueError, match="num_candidates must be at least 2, got 1"):
        module["main"](["num_candidates=1"])


def test_later_decisions_are_branched_and_distilled_into_files_of_their_own(script, tmp_path):
    module, calls = script
    module["main"]([f"out={tmp_path}", "tasks=[disassemble]", "decisions=4"])
    assert calls == STAGES
    assert (tmp_path / "benchmarks" / "scorer" / "distill" / "fm_disassemble_s0_d4.pt").exists()
    assert (tmp_path / "branched_d4" / "disassemble" / "fm_seed0" / "dropout" / "meta.json").exists()
    assert not (tmp_path / "benchmarks" / "scorer" / "fm_disassemble_s0.pt").exists()  # the first decision's name
    commands = dict((name, command) for name, _, command in module["stages"](
        module["Config"](out=str(tmp_path), decisions=4), "disassemble", 0))  # fmt: skip
    for stage in ("branching", "distillation"):
        script_config = runpy.run_path(commands[stage][1])["Config"]
        assert parse_config(script_config, commands[stage][2:]).decisions == 4


def test_another_number_of_candidates_is_branched_into_files_of_its_own(script, tmp_path):
    """K = 32 from the same first decisions is its own collection and files: the K = 8 run's complete branched
    folder and files, already there, do not count as its stages done."""
    module, calls = script
    module["main"]([f"out={tmp_path}", "tasks=[door]"])
    calls.clear()
    module["main"]([f"out={tmp_path}", "tasks=[door]", "num_candidates=32"])
    assert calls == STAGES[1:]  # the policy is shared
    assert (tmp_path / "branched_k32" / "door" / "fm_seed0" / "dropout" / "meta.json").exists()
    assert (tmp_path / "docs" / "results" / "honest_ceiling_fm_door_s0_k32.json").exists()
    assert (tmp_path / "benchmarks" / "scorer" / "distill" / "fm_door_s0_k32.pt").exists()
    commands = dict((name, command) for name, _, command in module["stages"](
        module["Config"](out=str(tmp_path), num_candidates=32, decisions=4), "door", 0))  # fmt: skip
    assert f"out={tmp_path / 'branched_d4_k32'}" in commands["branching"]
    assert "num_candidates=32" in commands["branching"] and "num_candidates=32" in commands["distillation"]


def test_evaluate_runs_the_ladder_the_screen_and_only_a_passed_screen_s_test(script, tmp_path):
    """With evaluate=true the preregistered protocol follows the files: a screen that wins as many episodes as it
    loses fails the rule, and its run's test episodes are never run, then or on resuming."""
    module, calls = script
    argv = [f"out={tmp_path}", "tasks=[disassemble,shelf-place]", "jobs=1", "evaluate=true"]
    module["main"](argv)
    evaluation = ["ladder", "screen", "test"]
    assert calls == STAGES + evaluation + STAGES + evaluation[:2]
    results = tmp_path / "docs" / "results"
    assert (results / "student_test_fm_disassemble_s0.json").exists()
    assert not (results / "student_test_fm_shelf_place_s0.json").exists()
    summary = json.loads((tmp_path / "scorer_benchmark_runs.json").read_text())
    assert summary["runs"][1]["stages"]["test"] == "screen failed"

    calls.clear()
    module["main"](argv)
    assert calls == []
    summary = json.loads((tmp_path / "scorer_benchmark_runs.json").read_text())
    assert [run["stages"]["test"] for run in summary["runs"]] == ["done before", "screen failed"]
