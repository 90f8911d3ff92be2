"""Evaluation videos (issue 16, item 8): TorchRL's VideoRecorder on RGB renders, written as GIFs."""

import pytest
import torch
from PIL import Image, ImageSequence

from torchrl_dalir.evaluation.video import VIDEO_FPS, VIDEO_SIZE, GifLogger

FRAME_MS = 1000 // VIDEO_FPS


def _frames(path):
    """The frames of a GIF, counting each merged run of identical frames by its duration."""
    with Image.open(path) as gif:
        durations = [frame.info["duration"] for frame in ImageSequence.Iterator(gif)]
        return sum(durations) // FRAME_MS, gif.size


def test_gif_logger_writes_every_frame_and_puts_several_videos_side_by_side(tmp_path):
    video = torch.arange(7, dtype=torch.uint8).mul(30).view(7, 1, 1, 1).expand(7, 3, 12, 16).contiguous()
    logger = GifLogger(tmp_path / "videos")
    logger.log_video("clip", video, step=3)
    logger.log_video("pair", torch.stack([video, video]))
    assert _frames(tmp_path / "videos" / "clip_3.gif") == (7, (16, 12))
    assert _frames(tmp_path / "videos" / "pair.gif") == (7, (32, 12))
    with pytest.raises(ValueError, match="uint8"):
        logger.log_video("clip", video.float())


def test_evaluation_records_the_first_episodes_of_each_method(trained_world_model, tmp_path):
    from torchrl_dalir.evaluation.compare import evaluate_checkpoints

    _, wm_path, policy_path = trained_world_model
    kwargs = dict(methods=["base", "dalir"], episodes=2, seed=1, num_candidates=3, max_steps=6, progress=False)
    rows = evaluate_checkpoints(policy_path, wm_path, video=1, video_dir=tmp_path / "videos", **kwargs)
    files = sorted(p.name for p in (tmp_path / "videos").iterdir())
    assert files == ["base_episode_0.gif", "dalir_episode_0.gif"]  # the first episode only
    for method, name in (("base", "base policy"), ("dalir", "DALI-R")):
        path = tmp_path / "videos" / f"{method}_episode_0.gif"
        steps = rows[name]["records"][0]["steps"]
        assert path.stat().st_size > 0 and _frames(path) == (
            steps + 1,
            (VIDEO_SIZE, VIDEO_SIZE),
        )  # the reset and every step
        with Image.open(path) as gif:
            assert len(gif.convert("L").getcolors(maxcolors=VIDEO_SIZE**2)) > 10  # a rendered scene, not a blank frame
    # recording changes no episode
    plain = evaluate_checkpoints(policy_path, wm_path, **kwargs)
    for name in ("base policy", "DALI-R"):
        assert [(r["steps"], r["episode_return"]) for r in plain[name]["records"]] == [
            (r["steps"], r["episode_return"]) for r in rows[name]["records"]
        ]
    with pytest.raises(ValueError, match="video_dir"):
        evaluate_checkpoints(policy_path, wm_path, video=1, **kwargs)


def test_evaluate_script_refuses_a_negative_number_of_videos():
    import importlib.util
    import sys
    from pathlib import Path

    from torchrl_dalir.config import parse_config

    spec = importlib.util.spec_from_file_location(
        "example_evaluate_video", Path(__file__).resolve().parents[1] / "examples" / "evaluate.py"
    )
    module = sys.modules[spec.name] = importlib.util.module_from_spec(spec)  # registered, so its annotations resolve
    spec.loader.exec_module(module)
    assert parse_config(module.Config, ["video=2"]).video == 2
    with pytest.raises(ValueError, match="video must be at least 0, got -1"):
        parse_config(module.Config, ["video=-1"])
