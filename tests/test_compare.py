import pytest

from torchrl_dalir.evaluation.compare import paired_sign_test


def test_paired_sign_test_counts_discordant_episodes_and_gives_the_exact_binomial_p_value():
    base = [True] * 10 + [False] * 3 + [True] * 7 + [False] * 30
    dalir = [False] * 10 + [True] * 3 + [True] * 7 + [False] * 30
    result = paired_sign_test(base, dalir)
    assert (result["base_only"], result["dalir_only"]) == (10, 3)
    # 2 * P(X <= 3), X ~ Binomial(13, 1/2) = 2 * (1 + 13 + 78 + 286) / 8192
    assert result["p_value"] == pytest.approx(756 / 8192)
    assert paired_sign_test(dalir, base)["p_value"] == result["p_value"]
    assert paired_sign_test([True, False], [True, False]) == {"base_only": 0, "dalir_only": 0, "p_value": 1.0}
    assert paired_sign_test([True, False, True], [False, True, True])["p_value"] == 1.0


def test_paired_sign_test_refuses_unpaired_results():
    with pytest.raises(ValueError, match="same episodes"):
        paired_sign_test([True, False], [True])


def test_decision_summary_reads_one_value_per_decision_from_a_receding_horizon_rollout():
    import torch
    from tensordict import TensorDict

    from torchrl_dalir.evaluation.compare import decision_summary, pool_decision_summaries
    from torchrl_dalir.reranking.actor import CANDIDATE_SCORES, CHOSEN_CANDIDATE

    scores = torch.tensor([[0.5, 0.7, 0.6], [0.4, 0.3, 0.2], [0.1, 0.1, 0.4]])
    chosen = torch.tensor([2, 0, 2])  # the first decision executes a candidate that is not the arg-max
    steps = torch.arange(20) // 8  # 20 steps, a decision every 8: 0, 8 and 16
    rollout = TensorDict({CANDIDATE_SCORES: scores[steps][None], CHOSEN_CANDIDATE: chosen[steps][None]}, [1, 20])
    summary = decision_summary(rollout, action_steps=8)
    assert summary["decisions"] == 3
    assert summary["clean_chosen"] == pytest.approx(1 / 3, abs=1e-4)
    assert summary["clean_score"] == pytest.approx(1 / 3, abs=1e-4)
    assert summary["chosen_margin"] == pytest.approx((0.1 + 0.0 + 0.3) / 3, abs=1e-4)  # the executed candidate's margin
    assert summary["score_spread"] == pytest.approx(
        (0.1 + 0.1 + 0.3 / 3**0.5) / 3, abs=1e-4
    )  # std([.1, .1, .4]) = 0.3 / sqrt(3)
    pooled = pool_decision_summaries([summary, {**summary, "decisions": 1, "clean_chosen": 1.0}])
    assert pooled["decisions"] == 4 and pooled["clean_chosen"] == pytest.approx((3 / 3 + 1.0) / 4, abs=1e-4)


def test_evaluate_checkpoints_refuses_unknown_methods_and_reranking_without_a_world_model():
    from torchrl_dalir.evaluation.compare import evaluate_checkpoints

    with pytest.raises(ValueError, match="unknown methods"):
        evaluate_checkpoints("policy.pt", "world_model.pt", methods=["base", "oracle"])
    with pytest.raises(ValueError, match="need a world_model_path"):
        evaluate_checkpoints("policy.pt", None, methods=["random"])


def test_the_point_dropout_policy_needs_no_world_model_replays_itself_and_plays_its_own_episodes(trained_policy):
    from torchrl_dalir.evaluation.compare import evaluate_checkpoints

    _, policy_path = trained_policy
    kwargs = dict(episodes=2, seed=1, progress=False, methods=["base", "dropout"])
    rows = evaluate_checkpoints(policy_path, None, **kwargs)
    again = evaluate_checkpoints(policy_path, None, **{**kwargs, "methods": ["dropout"]})["point-dropout policy"]
    outcomes = {name: [(r["steps"], r["episode_return"]) for r in row["records"]] for name, row in rows.items()}
    assert [(r["steps"], r["episode_return"]) for r in again["records"]] == outcomes[
        "point-dropout policy"
    ]  # seeded by actor_seed
    assert outcomes["point-dropout policy"] != outcomes["base policy"]  # perturbed views, its own noise: other actions


def test_summarize_evaluations_pairs_every_run_against_the_base_policy(tmp_path, monkeypatch, capsys):
    import json
    import runpy
    import sys
    from pathlib import Path

    def run(name, methods, seed=1):
        folder = tmp_path / "screen" / "stick-pull" / name
        folder.mkdir(parents=True)
        success = {
            m: {"success_rate": sum(s) / len(s), "selection": rule, "records": [{"success": x} for x in s]}
            for m, (rule, s) in methods.items()
        }
        (folder / "evaluation.json").write_text(
            json.dumps({"config": {"seed": seed, "episodes": 4}, "success": success})
        )

    run("a", {"base policy": ("", [True, True, False, False]), "random candidate": ("", [True, False, False, False])})
    run("b", {"DALI-R": ("argmax(ensemble)", [False, True, True, True])})
    script = Path(__file__).resolve().parents[1] / "examples" / "paper" / "summarize_evaluations.py"
    out = tmp_path / "summary.json"
    monkeypatch.setattr(sys, "argv", ["x", f"root={tmp_path / 'screen'}", f"out={out}"])
    runpy.run_path(str(script), run_name="__main__")
    methods = json.loads(out.read_text())["tasks"]["stick-pull"]["methods"]
    assert (methods["a/random candidate"]["base_only"], methods["a/random candidate"]["dalir_only"]) == (1, 0)
    assert (methods["b/DALI-R"]["base_only"], methods["b/DALI-R"]["dalir_only"]) == (1, 2)
    assert methods["b/DALI-R"]["success_rate"] == 0.75 and methods["b/DALI-R"]["selection"] == "argmax(ensemble)"
    assert "| | b/DALI-R | argmax(ensemble) | 75.0% | 1 / 2 | 1.00 |" in out.with_suffix(".md").read_text()
    run("c", {"DALI-R": ("argmax(state)", [True, True, True, True])}, seed=0)  # other episodes: refused
    with pytest.raises(ValueError, match="different episodes"):
        runpy.run_path(str(script), run_name="__main__")


def test_summarize_results_groups_seeds_by_world_model_variant(tmp_path, monkeypatch):
    import json
    import runpy
    import sys
    from pathlib import Path

    from torchrl_dalir.config import config_dict, parse_config
    from torchrl_dalir.pipeline import PRESETS, PipelineConfig

    def run(folder, seed, base, dalir):
        path = tmp_path / "results" / "stick-pull" / folder
        path.mkdir(parents=True)
        cfg = config_dict(
            parse_config(
                PipelineConfig, ["task=stick-pull", f"seed={seed}", "eval_episodes=4", f"out={tmp_path}"], PRESETS
            )
        )
        methods = {"base policy": base, "DALI-R": dalir, "DALI-R argmax": base, "random candidate": base}
        success = {
            m: {
                "success_rate": sum(s) / 4,
                "selection": "margin(ensemble, k=1, margin=1)",
                "records": [{"success": x} for x in s],
            }
            for m, s in methods.items()
        }
        (path / "results.json").write_text(json.dumps({"config": cfg, "success": success}))

    no, yes = [False] * 4, [True] * 4
    run("fm_seed0", 0, no, no)  # the paper's world model
    run("fm_seed0_frozen+explore_fm_seed0", 0, no, [True, False, False, False])
    run("fm_seed1_frozen+explore_fm_seed1", 1, no, yes)
    script = Path(__file__).resolve().parents[1] / "examples" / "paper" / "summarize_results.py"
    readme = tmp_path / "README.md"
    readme.write_text(
        "# Title\n<!-- table 1 -->\n**Caption.**\n\n| stale |\n<!-- end table 1 -->\n\n"
        "<!-- trusted-selection table -->\n**Rules.**\n\n| stale |\n\n<!-- end trusted-selection table -->\nEnd.\n"
    )
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "x",
            f"out={tmp_path}",
            "variant=frozen+explore",
            f"table1_json={tmp_path / 'tables' / 'table1.json'}",
            f"readme={readme}",
        ],
    )
    runpy.run_path(str(script), run_name="__main__")
    rows = {(r["variant"], tuple(r["seeds"])): r for r in json.loads((tmp_path / "summary.json").read_text())}
    assert sorted(rows) == [("frozen+explore", (0, 1)), ("paper", (0,))]
    assert (rows["frozen+explore", (0, 1)]["base_only"], rows["frozen+explore", (0, 1)]["dalir_only"]) == (0, 5)
    trusted = json.loads((tmp_path / "trusted_selection.json").read_text())
    assert trusted["variant"] == "frozen+explore" and trusted["tasks"]["stick-pull"]["seeds"] == 2
    assert trusted["tasks"]["stick-pull"]["default"] == 62.5 and trusted["mean_gain"] == 62.5
    table1 = json.loads((tmp_path / "tables" / "table1.json").read_text())  # the paper's Table 1, for the same variant
    assert table1 == json.loads((tmp_path / "table1.json").read_text())
    assert table1 == {
        "fm": {
            "stick-pull": {
                "base": [0.0, 0.0],
                "dalir": [25.0, 100.0],
                "seeds": [0, 1],
                "episodes": 4,
                "p": 0.0625,
                "rules": ["margin(ensemble, k=1, margin=1)"],
                "paper_base": 48.7,
                "paper_dalir": 50.7,
            }
        }
    }
    assert (
        "| fm | stick-pull | 2 x 4 | 0.0 +- 0.0 | 62.5 +- 37.5 | +62.5 | 0.062 |"
        in (tmp_path / "table1.md").read_text()
    )
    assert (tmp_path / "table1_fm.png").read_bytes() == (
        tmp_path / "tables" / "table1_fm.png"
    ).read_bytes()  # the plot beside the JSON too
    # the README's generated tables replaced, their captions and the text around them kept
    trusted_md, table1_md = (tmp_path / "trusted_selection.md").read_text(), (tmp_path / "table1.md").read_text()
    assert readme.read_text() == (
        f"# Title\n<!-- table 1 -->\n**Caption.**\n\n{table1_md.strip()}\n<!-- end table 1 -->\n\n"
        f"<!-- trusted-selection table -->\n**Rules.**\n\n{trusted_md.strip()}\n\n"
        "<!-- end trusted-selection table -->\nEnd.\n"
    )
    replace_region = runpy.run_path(str(script))["replace_region"]
    for wrong in (
        "<!-- end table 1 --> <!-- table 1 -->",
        "no markers",
        "<!-- table 1 --><!-- table 1 --><!-- end table 1 -->",
    ):
        with pytest.raises(ValueError, match="expected one <!-- table 1 -->"):
            replace_region(wrong, "table 1", "| new |")
    for no_caption in (
        "<!-- table 1 -->\n| old |\n<!-- end table 1 -->",
        "<!-- table 1 -->\n| old |\n\nafter\n<!-- end table 1 -->",
        "<!-- table 1 --><!-- end table 1 -->",
    ):  # a stale table would survive as the caption
        with pytest.raises(ValueError, match="must start with a caption paragraph"):
            replace_region(no_caption, "table 1", "| new |")


def test_summarize_results_adds_committed_records_to_the_runs_and_pools_their_discordant_episodes(
    tmp_path, monkeypatch
):
    import json
    import runpy
    import sys
    from pathlib import Path

    def record(seed, methods, **extra):
        return {
            "version": 1,
            "task": "pick-place-wall",
            "policy": "fm",
            "seed": seed,
            "variant": "frozen+explore",
            "run": f"run{seed}",
            "eval_seed": 0,
            "episodes": 4,
            "num_candidates": 32,
            "command": "",
            "commit": None,
            "methods": methods,
            **extra,
        }

    full = record(
        0,
        {
            "base": {"success_rate": 0.5, "outcomes": "1100"},
            "dalir": {"success_rate": 0.75, "outcomes": "1011", "selection": "argmax(state)"},
            "argmax": {"success_rate": 0.75, "outcomes": "1011"},
            "random": {"success_rate": 0.25, "outcomes": "0001"},
        },
    )
    # a run summarised before records existed: its discordant counts instead of its episodes
    counts = record(
        1,
        {
            "base": {"success_rate": 0.5},
            "dalir": {
                "success_rate": 0.5,
                "base_only": 0,
                "method_only": 0,
                "selection": "margin(ensemble, k=1, margin=1)",
            },
            "argmax": {"success_rate": 0.25, "base_only": 2, "method_only": 1},
            "random": {"success_rate": 0.5, "base_only": 1, "method_only": 1},
        },
        validation={
            "episodes": 30,
            "seed": 1,
            "alpha": 0.1,
            "base": 0.5,
            "chosen": "margin(ensemble, k=1, margin=1)",
            "entries": {"margin(ensemble, k=1, margin=1)": {"success_rate": 0.5, "base_only": 0, "method_only": 0}},
        },
    )
    folder = tmp_path / "runs"
    from torchrl_dalir.pipeline.records import load_records, save_records

    save_records([full, counts], folder)
    assert load_records([folder]) == [full, counts]
    with pytest.raises(ValueError, match="another run"):  # two different runs of one seed
        save_records([{**full, "methods": counts["methods"]}], folder)
    # the same run summarised again from a folder without its stage log keeps the timings it was saved with
    from torchrl_dalir.pipeline.records import merge_records

    timed = {
        **full,
        "seed": 5,
        "stage_seconds": {"policy": 60.0},
        "peak_memory_gib": 1.5,
        "workers_peak_memory_gib": 0.5,
    }
    [path] = save_records([timed], tmp_path / "timed")
    save_records([{**full, "seed": 5}], tmp_path / "timed")
    assert json.loads(path.read_text()) == timed
    assert merge_records([{**full, "seed": 5}], [timed]) == [timed] and merge_records(
        [timed], [{**full, "seed": 5}]
    ) == [timed]
    script = Path(__file__).resolve().parents[1] / "examples" / "paper" / "summarize_results.py"
    monkeypatch.setattr(
        sys, "argv", ["x", f"out={tmp_path / 'tables'}", f"records=[{folder}]", "variant=frozen+explore"]
    )
    runpy.run_path(str(script), run_name="__main__")
    row = json.loads((tmp_path / "tables" / "summary.json").read_text())[0]
    # seed 0: base 1100 vs DALI-R 1011 -> 1 / 2; seed 1: 0 / 0; arg-max 1 / 2 + 2 / 1; random 2 / 1 + 1 / 1
    assert row["discordant"] == {"dalir": [1, 2], "argmax": [3, 3], "random": [3, 2]}
    assert (row["base_only"], row["dalir_only"], row["p_value"]) == (1, 2, 1.0)
    trusted = json.loads((tmp_path / "tables" / "trusted_selection.json").read_text())["tasks"]["pick-place-wall"]
    assert (trusted["base"], trusted["default"], trusted["argmax"], trusted["random"]) == (50.0, 62.5, 50.0, 37.5)
    assert trusted["validation"] == {
        "1": {"episodes": 30, "seed": 1, "base": 50.0, "margin(ensemble, k=1, margin=1)": 50.0}
    }
    # arg-max 1011 against random 0001 on seed 0 (seed 1 kept no episodes): only the arg-max 2, only random 0
    assert trusted["argmax_vs_random"] == {"runs": 1, "random_only": 0, "argmax_only": 2, "p_value": 0.5}
    assert "only the arg-max 2, only the random pick 0" in (tmp_path / "tables" / "trusted_selection.md").read_text()
    summarize = runpy.run_path(str(script))
    dp = {**full, "policy": "dp", "task": "stick-pull"}
    table = summarize["gather"]([full, counts, dp])
    both = summarize["trusted_selection"](table, "frozen+explore")  # FM at the top level, DP under its name
    assert list(both["tasks"]) == ["pick-place-wall"] and list(both["dp"]["tasks"]) == ["stick-pull"]
    assert summarize["trusted_selection"](table, "frozen+explore", tasks=["pick-place-wall"])["tasks"] == both["tasks"]
    assert "dp" not in summarize["trusted_selection"](table, "frozen+explore", tasks=["pick-place-wall"])
    # a record whose counts contradict its success rates, or outcomes of another length, is refused
    with pytest.raises(ValueError, match="do not add up"):
        save_records(
            [
                {
                    **counts,
                    "seed": 2,
                    "methods": {**counts["methods"], "random": {"success_rate": 0.5, "base_only": 2, "method_only": 1}},
                }
            ],
            folder,
        )
    with pytest.raises(ValueError, match="4 characters"):
        save_records(
            [
                {
                    **full,
                    "seed": 3,
                    "methods": {**full["methods"], "random": {"success_rate": 0.25, "outcomes": "00001"}},
                }
            ],
            folder,
        )


def test_run_record_keeps_the_calibrations_confirmation_on_fresh_validation_episodes():
    from torchrl_dalir.pipeline.records import run_record

    config = {
        "task": "reach",
        "policy": "fm",
        "seed": 0,
        "eval_seed": 0,
        "eval_episodes": 2,
        "num_candidates": 4,
        "preset": "smoke",
        "out": "outputs",
    }
    result = {
        "config": config,
        "commit": "abc",
        "success": {"base policy": {"success_rate": 0.5, "records": [{"success": True}, {"success": False}]}},
    }
    entry = {"name": "argmax(state)", "success_rate": 0.6, "vs_base": {"base_only": 1, "dalir_only": 4}}
    calibration = {
        "episodes": 30,
        "seed": 1,
        "alpha": 0.1,
        "base_success_rate": 0.5,
        "chosen": "margin(ensemble, k=1, margin=1)",
        "entries": [entry],
        "confirmation": {
            "episodes": 30,
            "seed": 2,
            "entry": "argmax(state)",
            "base_success_rate": 0.4,
            "success_rate": 0.4333333,
            "vs_base": {"base_only": 3, "dalir_only": 4},
            "confirmed": False,
        },
    }
    validation = run_record(result, "fm_seed0", calibration)["validation"]
    assert validation["confirmation"] == {
        "episodes": 30,
        "seed": 2,
        "entry": "argmax(state)",
        "base": 0.4,
        "success_rate": 0.4333,
        "base_only": 3,
        "method_only": 4,
        "confirmed": False,
    }
    assert (
        "confirmation"
        not in run_record(result, "fm_seed0", {k: v for k, v in calibration.items() if k != "confirmation"})[
            "validation"
        ]
    )
    # the command names the calibration's alpha where it is not today's (a run from before the setting)
    assert "calibration_alpha" not in run_record(result, "fm_seed0", calibration)["command"]
    assert " calibration_alpha=1.0 " in run_record(result, "fm_seed0", {**calibration, "alpha": 1.0})["command"]


def test_run_record_of_a_calibration_sized_by_failures():
    from torchrl_dalir.pipeline.records import run_record

    config = {
        "task": "reach",
        "policy": "fm",
        "seed": 0,
        "eval_seed": 0,
        "eval_episodes": 2,
        "num_candidates": 4,
        "preset": "smoke",
        "out": "outputs",
    }
    result = {
        "config": config,
        "commit": "abc",
        "success": {"base policy": {"success_rate": 0.5, "records": [{"success": True}, {"success": False}]}},
    }
    calibration = {
        "design": "failures",
        "episodes": 40,
        "seed": 1,
        "alpha": 0.1,
        "base_success_rate": 0.75,
        "failed": [3, 9],
        "solved": [0, 1],
        "chosen": "argmax(state)",
        "entries": [{"name": "argmax(state)", "wins": 2, "losses": 0, "estimated_gain": 0.25, "seconds": 1.0}],
        "confirmation": {
            "episodes": 20,
            "seed": 2,
            "entry": "argmax(state)",
            "base_success_rate": 0.5,
            "success_rate": 0.75,
            "vs_base": {"base_only": 0, "dalir_only": 5},
            "confirmed": True,
        },
    }
    validation = run_record(result, "fm_seed0", calibration)["validation"]
    assert validation == {
        "design": "failures",
        "episodes": 40,
        "seed": 1,
        "alpha": 0.1,
        "base": 0.75,
        "failed": 2,
        "chosen": "argmax(state)",
        "entries": {"argmax(state)": {"wins": 2, "losses": 0, "estimated_gain": 0.25}},
        "confirmation": {
            "episodes": 20,
            "seed": 2,
            "entry": "argmax(state)",
            "base": 0.5,
            "success_rate": 0.75,
            "base_only": 0,
            "method_only": 5,
            "confirmed": True,
        },
    }
