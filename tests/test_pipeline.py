import json
import re
import runpy
import sys
from pathlib import Path

import pytest
import torch
from conftest import killed_at_the_complete_mark

from torchrl_dalir.pipeline import STAGES as PIPELINE_STAGES

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run_example(name, args, monkeypatch):
    monkeypatch.setattr(sys, "argv", [name, *args])
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")


@pytest.mark.parametrize("policy", ["fm"])
def test_main_job_smoke_runs_every_stage_and_skips_them_next_time(tmp_path, monkeypatch, capsys, policy):
    quiet = ["collection.progress=false", "policy_training.progress=false", "world_model.progress=false"]
    args = ["preset=smoke", "task=reach", f"policy={policy}", f"out={tmp_path}", *quiet]
    # the first run goes through the sweep: a separate process per task and seed
    run_example(
        "paper/sweep.py",
        [
            "tasks=[reach]",
            "seeds=[0]",
            f"policy={policy}",
            "preset=smoke",
            f"out={tmp_path}",
            "jobs=1",
            f"threads={torch.get_num_threads()}",
            f"overrides=[{','.join(quiet)}]",
        ],
        monkeypatch,
    )
    sweep = json.loads((tmp_path / "sweep.json").read_text())["runs"]
    assert [(r["task"], r["seed"], r["exit_code"]) for r in sweep] == [("reach", 0, 0)]
    log = (tmp_path / "logs" / f"reach_{policy}_seed0.log").read_text()
    # each stage's end names its time, artifact and the job's peak memory so far (which never falls)
    ends = re.findall(r"^\[(\w+)\] \d+ s -> .+ \(peak memory (\d+\.\d) GiB, workers \d+\.\d GiB\)$", log, re.MULTILINE)
    assert [stage for stage, _ in ends] == ["demos", "policy", "mixed", "world_model", "calibration", "evaluation"]
    peaks = [float(peak) for _, peak in ends]
    assert peaks == sorted(peaks) and peaks[0] > 0
    # its summary's trusted-selection table is of the runs' own world-model variant (smoke: the paper's)
    assert json.loads((tmp_path / "trusted_selection.json").read_text())["variant"] == "paper"
    results = tmp_path / "results" / "reach" / f"{policy}_seed0"
    data = json.loads((results / "results.json").read_text())
    assert list(data["success"]) == ["base policy", "DALI-R", "DALI-R argmax", "random candidate"]
    assert all(len(r["records"]) == 2 for r in data["success"].values())
    assert (results / "imagination.png").stat().st_size > 0
    assert (
        "| DALI-R |" in (results / "results.md").read_text()
        and "clean candidate kept in" in (results / "results.md").read_text()
    )
    # the rule chosen on validation episodes is stored in the world model, and DALI-R used it
    from torchrl_dalir.checkpoints import load_world_model

    calibration = json.loads((tmp_path / "calibration" / "reach" / f"{policy}_seed0" / "calibration.json").read_text())
    assert calibration["seed"] == 1 and calibration["episodes"] == 1
    world_model_path = tmp_path / "world_models" / policy / "reach" / "seed0" / "world_model.pt"
    assert (
        load_world_model(world_model_path).selection.name
        == calibration["chosen"]
        == data["success"]["DALI-R"]["selection"]
    )
    assert data["success"]["DALI-R argmax"]["selection"] == "argmax(state)"
    capsys.readouterr()
    run_example("train_dp3_wm.py", args, monkeypatch)
    assert capsys.readouterr().out.count("done before") == 6
    # examples/evaluate.py on the job's checkpoints replays the job's evaluation exactly (same thread count)
    policy_path = tmp_path / "policies" / "reach" / f"{policy}_seed0" / "checkpoint.pt"
    run_example(
        "evaluate.py",
        [
            f"policy_checkpoint={policy_path}",
            f"world_model={world_model_path}",
            "episodes=2",
            "num_candidates=4",
            f"out={tmp_path / 'evaluation'}",
        ],
        monkeypatch,
    )
    replay = json.loads((tmp_path / "evaluation" / "evaluation.json").read_text())["success"]
    for method in ("base policy", "DALI-R"):
        assert replay[method]["records"] == data["success"][method]["records"]
    assert (tmp_path / "evaluation" / "evaluation.csv").read_text().count("\n") == 1 + 4
    # the candidates' imagined against their real outcomes, on the same checkpoints
    diagnosis = tmp_path / "candidate_outcomes"
    run_example(
        "paper/diagnose_reranking.py",
        [
            f"policy_checkpoint={policy_path}",
            f"world_model={world_model_path}",
            "episodes=1",
            "decisions=2",
            "num_candidates=4",
            f"out={diagnosis}",
        ],
        monkeypatch,
    )
    outcomes = json.loads((diagnosis / "candidate_outcomes.json").read_text())
    assert outcomes["summary"]["decisions"] == 2 and [len(r["real_score"]) for r in outcomes["records"]] == [4, 4]
    assert (diagnosis / "candidate_outcomes.png").stat().st_size > 0
    with pytest.raises(FileNotFoundError, match="no policy checkpoint at"):
        run_example(
            "paper/diagnose_reranking.py",
            [f"policy_checkpoint={tmp_path / 'missing.pt'}", f"world_model={world_model_path}"],
            monkeypatch,
        )
    records = tmp_path / "records"  # the sweep's summary, again, keeping the run's record
    run_example("paper/summarize_results.py", [f"out={tmp_path}", f"save_records={records}"], monkeypatch)
    record = json.loads((records / "paper" / "reach" / f"{policy}_seed0.json").read_text())
    assert record["methods"]["dalir"]["outcomes"] == "".join(
        "1" if r["success"] else "0" for r in data["success"]["DALI-R"]["records"]
    )
    assert record["validation"]["chosen"] == calibration["chosen"] and record["commit"] == data["commit"]
    # every finished stage's wall time and peak memory, logged under out and kept in the record
    stage_file = tmp_path / "stages" / "reach" / f"{policy}_seed0.jsonl"
    stages = [json.loads(line) for line in stage_file.read_text().splitlines()]
    assert [s["stage"] for s in stages] == [stage for stage, _ in ends] and {s["run"] for s in stages} == {
        f"reach/{policy}_seed0"
    }
    assert all(
        abs(s["peak_memory_gib"] - float(peak)) < 0.06 for s, (_, peak) in zip(stages, ends)
    )  # the log's numbers
    assert (
        record["stage_seconds"] == {s["stage"]: s["seconds"] for s in stages}
        and record["peak_memory_gib"] == stages[-1]["peak_memory_gib"]
    )
    assert record["workers_peak_memory_gib"] == max(s["workers_peak_memory_gib"] for s in stages)
    costs = (tmp_path / "run_costs.md").read_text().splitlines()
    assert (
        len(costs) == 5
        and costs[2].startswith(f"| {policy} | reach | paper | 0 | ")
        and costs[4].startswith("A blank stage")
    )
    assert (
        costs[2].split(" | ")[4 + PIPELINE_STAGES.index("exploration")] == ""
    )  # the smoke job collects no exploration data
    # the record's command, run in another folder, is this run's configuration
    from torchrl_dalir.config import config_dict, parse_config
    from torchrl_dalir.pipeline import PRESETS, PipelineConfig

    assert record[
        "command"
    ] == f"python examples/train_dp3_wm.py task=reach seed=0 policy={policy} preset=smoke " + " ".join(quiet)
    again = parse_config(PipelineConfig, [*record["command"].split()[2:], f"out={tmp_path}"], PRESETS)
    assert json.loads(json.dumps(config_dict(again))) == data["config"]  # (JSON holds tuples as lists)
    # the record alone (the run folder gone) gives the same summary
    alone = tmp_path / "from_records"
    run_example("paper/summarize_results.py", [f"out={alone}", f"records=[{records}]"], monkeypatch)
    assert json.loads((alone / "summary.json").read_text()) == json.loads((tmp_path / "summary.json").read_text())
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert [(r["task"], r["policy"], r["seeds"]) for r in summary] == [("reach", policy, [0])]
    assert summary[0]["dalir"] == [data["success"]["DALI-R"]["success_rate"]]
    pairs = list(zip(*(data["success"][m]["records"] for m in ("base policy", "DALI-R"))))
    assert summary[0]["base_only"] == sum(b["success"] and not d["success"] for b, d in pairs)
    assert summary[0]["dalir_only"] == sum(d["success"] and not b["success"] for b, d in pairs)
    assert (tmp_path / f"summary_{policy}.png").stat().st_size > 0
    trusted = json.loads((tmp_path / "trusted_selection.json").read_text())  # the trusted-selection table's data
    reach = trusted["tasks"]["reach"]
    assert (reach["seeds"], reach["episodes"], reach["rules"]) == (1, 2, {"0": calibration["chosen"]})
    for key, method in (
        ("base", "base policy"),
        ("default", "DALI-R"),
        ("argmax", "DALI-R argmax"),
        ("random", "random candidate"),
    ):
        assert reach[key] == 100 * data["success"][method]["success_rate"]
    assert trusted["default_rule"] == calibration["chosen"].split("(")[0] and trusted["mean_gain"] == round(
        reach["default"] - reach["base"], 1
    )
    assert (tmp_path / f"trusted_selection_{policy}.png").stat().st_size > 0
    # an interrupted policy training (its checkpoint short of the last step) is resumed, not skipped
    checkpoint = tmp_path / "policies" / "reach" / f"{policy}_seed0" / "checkpoint.pt"
    state = torch.load(checkpoint, weights_only=False)
    state["step"] -= 1
    torch.save(state, checkpoint)
    run_example("train_dp3_wm.py", args, monkeypatch)
    out = capsys.readouterr().out
    assert "[policy] done before" not in out and out.count("done before") == 5
    assert torch.load(checkpoint, weights_only=False)["step"] == state["num_steps"]
    from torchrl_dalir.pipeline.records import stage_log

    with open(stage_file, "a") as log:  # a line cut short by a crash is skipped
        log.write('{"run": "reach/')
    lines = [json.loads(line) for line in stage_file.read_text().splitlines()[:-1]]
    assert [s["stage"] for s in lines].count("policy") == 2  # the resumed stage's second line counts
    assert stage_log(tmp_path)[f"reach/{policy}_seed0"]["policy"] == [s for s in lines if s["stage"] == "policy"][-1]
    # redoing a stage starts it and every later stage from scratch, keeping the previous runs aside
    run_example("train_dp3_wm.py", [*args, "redo=[world_model]"], monkeypatch)
    out = capsys.readouterr().out
    assert (
        "[world_model] redo" in out
        and "[calibration] redo" in out
        and "[evaluation] redo" in out
        and out.count("done before") == 3
    )
    assert len(list((tmp_path / "world_models" / policy / "reach").glob("seed0.replaced-*"))) == 1
    # the redo's lines follow the cut one on lines of their own, and its stages' last lines count
    after_cut = stage_file.read_text().splitlines()[len(lines) + 1 :]
    assert [json.loads(line)["stage"] for line in after_cut] == ["world_model", "calibration", "evaluation"]
    assert stage_log(tmp_path)[f"reach/{policy}_seed0"]["world_model"] == json.loads(after_cut[0])


def test_sweep_refuses_unknown_tasks_before_running_anything(tmp_path, monkeypatch):
    with pytest.raises(KeyError, match="unknown task 'shelf_place'"):
        run_example("paper/sweep.py", ["tasks=[shelf_place]", f"out={tmp_path}"], monkeypatch)
    assert not (tmp_path / "logs").exists()


def test_exploration_rollouts_join_the_world_models_data(tmp_path, monkeypatch):
    from torchrl_dalir.checkpoints import load_world_model
    from torchrl_dalir.data import TrajectoryDataset

    quiet = ["collection.progress=false", "policy_training.progress=false", "world_model.progress=false"]
    run_example(
        "train_dp3_wm.py",
        ["preset=smoke", "task=reach", f"out={tmp_path}", "exploration_rollouts=2", "until=world_model", *quiet],
        monkeypatch,
    )
    explore = TrajectoryDataset.load(tmp_path / "data" / "reach" / "explore_fm_seed0")
    assert explore.num_trajectories == 2 and explore.meta.sources[0]["name"] == "exploration"
    mixed = TrajectoryDataset.load(tmp_path / "data" / "reach" / "mixed_fm_seed0")
    parts = load_world_model(tmp_path / "world_models" / "fm" / "reach" / "seed0+explore_fm_seed0" / "world_model.pt")
    held = len(parts.held_out_trajectories)
    assert held == round(0.4 * (mixed.num_trajectories + 2))  # the split runs over both datasets' trajectories
    assert not (tmp_path / "calibration").exists()  # stopped after the world model


def test_branched_stage_collects_ranks_and_is_skipped_next_time(tmp_path, monkeypatch, capsys):
    quiet = ["collection.progress=false", "policy_training.progress=false", "world_model.progress=false"]
    args = [
        "preset=smoke",
        "task=reach",
        f"out={tmp_path}",
        "branched_episodes=2",
        "branched_stride=25",
        "branched_candidates=2",
        "until=branched",
        *quiet,
    ]
    run_example("train_dp3_wm.py", args, monkeypatch)
    folder = tmp_path / "data" / "reach" / "branched_fm_seed0"
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["complete"] and (meta["candidates"], meta["num_candidates"], meta["seed"]) == (
        "dropout",
        2,
        900_000_000,
    )
    ranking = json.loads((folder / "ranking.json").read_text())
    assert ranking["train_decisions"] == 2  # decision 0 of each episode, all of them trained on
    assert ranking["variant"] in ("outcome", "ranking") and set(ranking["out_of_fold"]) == {"outcome", "ranking"}
    from torchrl_dalir.checkpoints import load_chunk_critic, load_policy

    policy = load_policy(tmp_path / "policies" / "reach" / "fm_seed0" / "checkpoint.pt")
    critic_metrics = load_chunk_critic(folder / "critic.pt", policy=policy).metrics
    assert json.dumps(critic_metrics, sort_keys=True) == json.dumps(ranking, sort_keys=True)  # NaN AUCs compare as text
    assert not (tmp_path / "world_models").exists()  # stopped after the branched stage
    capsys.readouterr()
    run_example("train_dp3_wm.py", args, monkeypatch)
    assert "[branched] done before" in capsys.readouterr().out
    with pytest.raises(ValueError, match="branched_candidates"):
        run_example("train_dp3_wm.py", [*args, "branched_candidates=1"], monkeypatch)


def test_main_job_resumes_a_dataset_killed_before_its_complete_mark(tmp_path, monkeypatch, capsys):
    """A kill between the rename of a dataset's rows and its ``complete`` mark leaves rows on disk but an incomplete
    dataset: the main job does not count that stage as done, and the re-run finishes the dataset."""
    from torchrl_dalir.data import TrajectoryDataset, storage

    args = ["preset=smoke", "task=reach", f"out={tmp_path}", "until=demos", "collection.progress=false"]
    with killed_at_the_complete_mark(), pytest.raises(KeyboardInterrupt):
        run_example("train_dp3_wm.py", args, monkeypatch)
    demos = tmp_path / "data" / "reach" / "demos"
    assert (demos / "rows").is_dir() and not storage.is_complete(demos)
    capsys.readouterr()
    run_example("train_dp3_wm.py", args, monkeypatch)
    assert "done before" not in capsys.readouterr().out
    assert TrajectoryDataset.load(demos).num_trajectories == 2
    run_example("train_dp3_wm.py", args, monkeypatch)
    assert "[demos] done before" in capsys.readouterr().out


def test_the_cpu_preset_is_the_reranking_protocol_and_run_commands_name_only_departures():
    from torchrl_dalir.config import config_dict, parse_config
    from torchrl_dalir.pipeline import PRESETS, PipelineConfig
    from torchrl_dalir.pipeline.records import command

    def run(*overrides):
        cfg = parse_config(
            PipelineConfig, ["task=stick-pull", "seed=1", "policy=dp", "out=/tmp/x", *overrides], PRESETS
        )
        return cfg, json.loads(json.dumps(config_dict(cfg)))

    cfg, config = run()
    protocol = (
        cfg.policy_training.num_steps,
        cfg.world_model.encoder,
        cfg.exploration_rollouts,
        cfg.calibration_grid,
        cfg.calibration_confirm_episodes,
    )
    assert protocol == (1000, "frozen", 60, "argmax", 0)
    assert cfg.run_name() == "dp_seed1_frozen+explore_dp_seed1"  # the folder of runs that set the protocol by hand
    head = "python examples/train_dp3_wm.py task=stick-pull seed=1 policy=dp preset=cpu"
    assert command(config) == head
    # a run of the earlier protocol names what it set apart from today's preset
    _, old = run(
        "policy_training.num_steps=2000",
        "world_model.encoder=finetune",
        "exploration_rollouts=0",
        "calibration_grid=all",
        "calibration_confirm_episodes=30",
    )
    assert command(old) == (
        f"{head} exploration_rollouts=0 calibration_confirm_episodes=30 calibration_grid=all "
        "policy_training.num_steps=2000 world_model.encoder=finetune"
    )
    # a run made before a setting existed ran at the value it was added with (here: no exploration, all nine settings)
    older = {key: value for key, value in old.items() if key not in ("exploration_rollouts", "calibration_grid")}
    assert command(older) == command(old)
    with pytest.warns(
        UserWarning, match="set calibration_confirm_episodes=30"
    ):  # nine settings, the luckiest unconfirmed
        run("calibration_grid=all")
    # exploration data named by hand (none collected) is a departure too
    _, by_hand = run("exploration_rollouts=0", "world_model.extra_data=[explore_dp_seed1]")
    assert command(by_hand) == f"{head} exploration_rollouts=0 world_model.extra_data=[explore_dp_seed1]"
    assert parse_config(PipelineConfig, ["preset=paper"], PRESETS).exploration_rollouts == 0


def test_a_training_stage_refuses_a_checkpoint_trained_with_other_settings(tmp_path):
    from torchrl_dalir.checkpoints import training_finished
    from torchrl_dalir.config import config_dict, parse_config
    from torchrl_dalir.pipeline import PRESETS, PipelineConfig
    from torchrl_dalir.pipeline.run import trained_as_asked

    def job(*overrides):
        return parse_config(
            PipelineConfig, ["preset=smoke", "task=reach", "policy=dp", f"out={tmp_path}", *overrides], PRESETS
        )

    trained = job().policy_training
    assert trained.model.kind == "dp"  # named by the job's policy, before any training
    path = tmp_path / "checkpoint.pt"
    assert not trained_as_asked("policy", trained, training_finished)(path)  # nothing yet: train
    torch.save({"config": config_dict(trained), "step": 30, "num_steps": 30}, path)
    assert trained_as_asked("policy", trained, training_finished)(path)
    # where it writes, its device and logging do not matter; what it learns does
    assert trained_as_asked(
        "policy", job("device=cuda", "policy_training.log_every=7").policy_training, training_finished
    )(path)
    with pytest.raises(ValueError, match=r"trained with num_steps=30 \(this job: 60\): pass redo=\[policy\]"):
        trained_as_asked("policy", job("policy_training.num_steps=60").policy_training, training_finished)(path)
    with pytest.raises(ValueError, match=r"model=.*'kind': 'dp'.*\(this job: .*'kind': 'fm'"):
        trained_as_asked("policy", job("policy=fm").policy_training, training_finished)(path)
    torch.save({"config": config_dict(trained), "step": 10, "num_steps": 30}, path)  # interrupted: resumed, not refused
    assert not trained_as_asked("policy", trained, training_finished)(path)
    # FM's target: a checkpoint records the task's (resolved) one, which a job that leaves it to the task asks for
    fm = job("policy=fm").policy_training
    assert (fm.model.flow_prediction, fm.resolved().model.flow_prediction) == ("task", "velocity")
    torch.save({"config": config_dict(fm.resolved()), "step": 30, "num_steps": 30}, path)
    assert trained_as_asked("policy", fm.resolved(), training_finished)(path)
    with pytest.raises(ValueError, match=r"'flow_prediction': 'velocity'.*\(this job: .*'flow_prediction': 'sample'"):
        trained_as_asked(
            "policy",
            job("policy=fm", "policy_training.model.flow_prediction=sample").policy_training.resolved(),
            training_finished,
        )(path)


def test_main_job_calibration_design_failures_calls_calibrate_on_failures(tmp_path, monkeypatch):
    from torchrl_dalir.config import parse_config
    from torchrl_dalir.evaluation import calibration
    from torchrl_dalir.pipeline import PRESETS, PipelineConfig, run
    from torchrl_dalir.reranking import RerankingConfig

    calls = []

    def fake(policy_path, world_model_path, **kwargs):
        calls.append(kwargs)
        return {"design": "failures", "episodes": 40, "chosen": "margin(ensemble, k=1, margin=1)"}

    monkeypatch.setattr(run, "calibrate_on_failures", fake)
    cfg = parse_config(
        PipelineConfig,
        [
            "preset=cpu",
            "seed=2",
            "calibration_design=failures",
            "calibration_failures=7",
            "calibration_grid=all",
            f"out={tmp_path}",
        ],
        PRESETS,
    )
    run.calibrate_and_record(cfg, tmp_path / "p.pt", tmp_path / "w.pt", tmp_path / "calibration.json")
    reranking = RerankingConfig(num_candidates=32, dropout=0.2, common_noise=True)  # the evaluations' common noise
    assert calls == [
        {
            "failures": 7,
            "grid": calibration.GRIDS["all"],
            "alpha": calibration.ALPHA,
            "seed": 1,
            "test_seed": 0,
            "device": "cpu",
            "reranking": reranking,
            "actor_seed": 2,
            "critic": None,  # no branched stage, no critic
        }
    ]
    assert json.loads((tmp_path / "calibration.json").read_text())["episodes"] == 40
    with pytest.raises(ValueError, match="calibration_design must be one of"):
        parse_config(PipelineConfig, ["calibration_design=adaptive"], PRESETS)
    with pytest.raises(ValueError, match="would be the test episodes"):  # its confirmation reads calibration_seed + 1
        parse_config(PipelineConfig, ["calibration_design=failures", "calibration_seed=2", "eval_seed=3"], PRESETS)
