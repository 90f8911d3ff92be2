"""Logging a user chooses (issue 40): CSV always, wandb only when asked for (off | offline | online)."""

import pytest

from torchrl_dalir.config import parse_config
from torchrl_dalir.pipeline import PRESETS, PipelineConfig
from torchrl_dalir.training import (
    POLICY_PRESETS,
    WORLD_MODEL_PRESETS,
    PolicyTrainingConfig,
    WorldModelTrainingConfig,
    train_policy,
)


def test_by_default_a_training_writes_csv_and_no_wandb_run(collected, tmp_path):
    data = tmp_path / "data"
    (data / "reach").mkdir(parents=True)
    (data / "reach" / "demos").symlink_to(collected.root)
    smoke = {key: value for key, value in POLICY_PRESETS["smoke"].items() if key != "wandb"}  # the default
    argv = [
        "preset=smoke",
        "task=reach",
        f"data={data}",
        f"out={tmp_path / 'policies'}",
        "progress=false",
        "num_steps=10",
    ]
    cfg = parse_config(PolicyTrainingConfig, argv, {"smoke": smoke})
    assert cfg.wandb == "off"
    train_policy(cfg)
    run_dir = cfg.run_dir()
    assert not list(run_dir.rglob("wandb")) and not (tmp_path / "wandb").exists()
    scalars = run_dir / "logs" / "reach_fm_seed0" / "scalars"
    assert (scalars / "loss_flow_matching.csv").read_text().startswith("10,")  # step 10 (log_every=10)
    assert (scalars / "lr.csv").exists()


MODES = [
    ("off", "off"),
    ("offline", "offline"),
    ("online", "online"),
    ("ONLINE", "online"),
    ("true", "offline"),
    ("false", "off"),
    ("on", "offline"),
]  # OmegaConf reads off / on as booleans


@pytest.mark.parametrize(("given", "mode"), MODES)
def test_wandb_takes_a_mode_or_the_old_booleans_from_a_command_line(given, mode):
    assert parse_config(PolicyTrainingConfig, [f"wandb={given}"], POLICY_PRESETS).wandb == mode
    assert parse_config(WorldModelTrainingConfig, [f"wandb={given}"], WORLD_MODEL_PRESETS).wandb == mode


def test_stored_boolean_configs_and_the_presets_booleans_still_work():
    assert PolicyTrainingConfig(wandb=True).wandb == "offline" and PolicyTrainingConfig(wandb=False).wandb == "off"
    assert WorldModelTrainingConfig(wandb=True).wandb == "offline"
    for presets, config in ((POLICY_PRESETS, PolicyTrainingConfig), (WORLD_MODEL_PRESETS, WorldModelTrainingConfig)):
        assert presets["smoke"]["wandb"] is False
        assert parse_config(config, ["preset=smoke"], presets).wandb == "off"
        assert parse_config(config, ["preset=smoke", "wandb=offline"], presets).wandb == "offline"


def test_the_main_jobs_wandb_setting_reaches_both_trainings():
    cfg = parse_config(PipelineConfig, ["preset=smoke", "wandb=offline"], PRESETS)  # the smoke presets say wandb: False
    assert (cfg.wandb, cfg.policy_training.wandb, cfg.world_model.wandb) == ("offline", "offline", "offline")
    cfg = parse_config(PipelineConfig, ["preset=cpu"], PRESETS)
    assert (cfg.wandb, cfg.policy_training.wandb, cfg.world_model.wandb) == ("off", "off", "off")
    with pytest.raises(ValueError, match="policy_training.wandb='online' would be replaced by the main job's 'off'"):
        parse_config(PipelineConfig, ["policy_training.wandb=online"], PRESETS)


@pytest.mark.parametrize(
    ("config", "presets", "argv"),
    [
        (PolicyTrainingConfig, POLICY_PRESETS, ["wandb=maybe"]),
        (WorldModelTrainingConfig, WORLD_MODEL_PRESETS, ["wandb=1"]),
        (PipelineConfig, PRESETS, ["wandb=cloud"]),
        (PipelineConfig, PRESETS, ["world_model.wandb=sometimes"]),
    ],
)
def test_an_invalid_wandb_value_is_refused_naming_the_setting(config, presets, argv):
    with pytest.raises(ValueError, match=r"wandb must be one of \['off', 'offline', 'online'\], got"):
        parse_config(config, argv, presets)


@pytest.mark.parametrize("wandb", ["off", "offline"])
def test_the_main_jobs_calibration_results_go_to_wandb_only_when_asked(wandb, tmp_path, monkeypatch):
    from torchrl_dalir.pipeline.run import log_calibration

    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = parse_config(PipelineConfig, ["preset=smoke", "task=reach", f"out={tmp_path}", f"wandb={wandb}"], PRESETS)
    vs_base = {"base_only": 0, "dalir_only": 3, "p_value": 0.25}
    record = {
        "episodes": 3,
        "seed": 1,
        "alpha": 0.1,
        "base_success_rate": 0.0,
        "chosen": "argmax(ensemble)",
        "entries": [{"name": "argmax(ensemble)", "success_rate": 1.0, "vs_base": vs_base}],
    }
    log_calibration(cfg, record)
    runs = list(cfg.calibration_dir().glob("wandb/offline-run-*/run-*.wandb"))
    assert len(runs) == (wandb == "offline")
    assert not (cfg.calibration_dir() / "logs").exists()  # no CSV: calibration.json holds the numbers
    if runs:
        import wandb as wandb_lib

        wandb_lib.finish()
