"""Bad settings and bad files fail at once, with a message that names them."""

import dataclasses

import pytest
import torch

from torchrl_dalir.checkpoints import load_checkpoint
from torchrl_dalir.config import parse_config
from torchrl_dalir.data.config import PRESETS as COLLECTION_PRESETS
from torchrl_dalir.data.config import CollectionConfig
from torchrl_dalir.pipeline import PRESETS, PipelineConfig


@pytest.mark.parametrize(
    ("argv", "error", "message"),
    [
        (["epochz=3"], ValueError, "bad setting 'epochz'.*the settings here are task, preset, seed"),
        (
            ["policy_training.model.foo=1"],
            ValueError,
            "'policy_training.model.foo'.*settings of 'policy_training.model' are kind, horizon",
        ),
        (["eval_episodes=ten"], ValueError, "bad setting 'eval_episodes': Value 'ten'"),
        (["preset=gpu"], ValueError, r"unknown preset 'gpu'; choose one of \['cpu', 'paper', 'smoke'\]"),
        (["policy=xyz"], ValueError, r"policy must be one of \['dp', 'fm'\], got 'xyz'"),
        (["task=dissasemble"], KeyError, "unknown task 'dissasemble'. Benchmark tasks: .*'disassemble'"),
        (["redo=[policies]"], ValueError, "unknown stages"),
    ],
)
def test_bad_settings_fail_with_a_clear_message(argv, error, message):
    with pytest.raises(error, match=message):
        parse_config(PipelineConfig, argv, PRESETS)


def test_good_settings_reach_the_nested_stages():
    cfg = parse_config(
        PipelineConfig,
        ["task=stick-pull", "policy=dp", "preset=smoke", "seed=2", "policy_training.model.ddim_steps=3"],
        PRESETS,
    )
    assert (cfg.policy_training.task, cfg.policy_training.policy, cfg.policy_training.seed) == ("stick-pull", "dp", 2)
    assert cfg.policy_training.model.ddim_steps == 3 and cfg.collection.mixed_name == "mixed_dp_seed2"
    with pytest.raises(ValueError, match="stage must be one of"):
        parse_config(CollectionConfig, ["stage=everything"], COLLECTION_PRESETS)


def test_load_checkpoint_explains_directories_and_foreign_files(tmp_path):
    torch.save({"kind": "policy"}, tmp_path / "checkpoint.pt")
    assert load_checkpoint(tmp_path / "checkpoint.pt", "policy") == {"kind": "policy"}
    with pytest.raises(IsADirectoryError, match=r"pass the policy checkpoint file in it \(\['checkpoint.pt'\]\)"):
        load_checkpoint(tmp_path, "policy")
    with pytest.raises(ValueError, match="is not a torchrl_dalir world_model checkpoint"):
        load_checkpoint(tmp_path / "checkpoint.pt", "world_model")
    (tmp_path / "meta.json").write_text('{"task": "reach"}')
    with pytest.raises(ValueError, match="meta.json is not a torchrl_dalir policy checkpoint"):
        load_checkpoint(tmp_path / "meta.json", "policy")
    with pytest.raises(FileNotFoundError, match="no policy checkpoint"):
        load_checkpoint(tmp_path / "missing.pt", "policy")


def test_the_main_job_refuses_stage_settings_it_would_replace():
    with pytest.raises(
        ValueError,
        match=(
            "policy_training.device='cuda' would be replaced by the main job's 'cpu', "
            "which it derives from its own device"
        ),
    ):
        parse_config(PipelineConfig, ["policy_training.device=cuda"], PRESETS)
    with pytest.raises(ValueError, match="world_model.policy_checkpoint='/tmp/other.pt' .* out, policy and seed"):
        parse_config(PipelineConfig, ["world_model.policy_checkpoint=/tmp/other.pt"], PRESETS)
    cfg = parse_config(
        PipelineConfig, ["device=cuda", "task=shelf-place", "seed=2", "out=/tmp/x", "policy=dp"], PRESETS
    )
    assert (cfg.policy_training.device, cfg.world_model.device) == ("cuda", "cuda")
    assert cfg.world_model.policy_checkpoint == "/tmp/x/policies/shelf-place/dp_seed2/checkpoint.pt"
    assert cfg.collection.mixed_name == cfg.world_model.mixed_name == "mixed_dp_seed2"
    assert dataclasses.replace(cfg) == cfg  # a built configuration validates again unchanged


def test_the_fm_target_is_the_tasks_unless_named_and_velocity_on_adroit_warns():
    import warnings

    from torchrl_dalir.modules import PolicyConfig, make_policy
    from torchrl_dalir.pipeline.config import PRESETS as PIPELINE_PRESETS
    from torchrl_dalir.pipeline.config import PipelineConfig
    from torchrl_dalir.training.policy import PRESETS as POLICY_PRESETS
    from torchrl_dalir.training.policy import PolicyTrainingConfig

    def target(args, config_class=PolicyTrainingConfig, presets=POLICY_PRESETS):
        cfg = parse_config(config_class, args, presets)
        cfg = getattr(cfg, "policy_training", cfg)
        return cfg.model.flow_prediction, cfg.resolved().model.flow_prediction

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert target(["task=door", "policy=fm"]) == ("task", "sample")
        assert target(["task=pen", "policy=dp"]) == ("task", "sample")  # DP ignores it
        assert target(["task=disassemble", "policy=fm"]) == ("task", "velocity")
        assert target(["task=door", "policy=fm", "model.flow_prediction=sample"]) == ("sample", "sample")
        assert target(["task=disassemble", "policy=fm", "model.flow_prediction=sample"]) == ("sample", "sample")
        # the main job sets its stages' task after their defaults were built: still the task's target
        assert target(["task=door", "policy=fm"], PipelineConfig, PIPELINE_PRESETS) == ("task", "sample")
        assert target(["task=stick-pull", "policy=fm"], PipelineConfig, PIPELINE_PRESETS) == ("task", "velocity")
    with pytest.warns(UserWarning, match="velocity target"):
        assert target(["task=door", "policy=fm", "model.flow_prediction=velocity"]) == ("velocity", "velocity")
    with pytest.raises(ValueError, match="names no target"):
        make_policy(PolicyConfig(flow_prediction="task"), action_dim=4, state_dim=4)
