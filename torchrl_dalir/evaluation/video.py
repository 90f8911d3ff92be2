"""Evaluation videos: TorchRL's ``VideoRecorder`` on an env that renders RGB frames, written as GIFs.

TorchRL writes MP4 through ``torchcodec`` (an FFmpeg binding, not a dependency of TorchRL or of
this library); :class:`GifLogger` writes the recorder's videos as animated GIFs with Pillow
(already installed with matplotlib), so recording needs nothing more.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
from PIL import Image
from torchrl.record import VideoRecorder
from torchrl.record.loggers import Logger

from torchrl_dalir import keys

VIDEO_SIZE = 128  # side of the square RGB frames, in pixels (within every task's offscreen buffer)
VIDEO_FPS = 25  # GIF frame delays are hundredths of a second: 25 frames per second is exact (4)


class GifLogger(Logger):
    """A TorchRL logger that writes each video as an animated GIF, ``<log_dir>/<name>_<step>.gif``
    (``<name>.gif`` without a step); it logs nothing else.

    Args:
        log_dir: the folder of the GIFs (created when the first one is written).
        fps: frames per second (``VideoRecorder(fps=...)`` overrides it per video).

    Example:
        >>> import tempfile
        >>> logger = GifLogger(tempfile.mkdtemp())
        >>> logger.log_video("episode", torch.zeros(1, 10, 3, 16, 16, dtype=torch.uint8), step=0)
        >>> sorted(p.name for p in Path(logger.log_dir).iterdir())
        ['episode_0.gif']
    """

    def __init__(self, log_dir: str | Path, fps: int = VIDEO_FPS):
        self.fps = fps
        super().__init__(exp_name="videos", log_dir=str(log_dir))

    def _create_experiment(self) -> None:
        return None

    def log_video(
        self, name: str, video: torch.Tensor, step: int | None = None, fps: int | None = None, **kwargs
    ) -> None:
        """Writes ``video`` ``[T, C, H, W]`` or ``[N, T, C, H, W]`` (``N`` videos side by side),
        uint8 with ``C`` 1 or 3, as one GIF."""
        if video.dim() == 5:
            video = torch.cat(list(video), dim=-1)
        if video.dim() != 4 or video.shape[1] not in (1, 3) or video.dtype != torch.uint8:
            raise ValueError(
                "a video must be uint8 [T, C, H, W] or [N, T, C, H, W] with C 1 or 3, "
                f"got {video.dtype} {tuple(video.shape)}"
            )
        frames = [Image.fromarray(frame.numpy()) for frame in video.expand(-1, 3, -1, -1).permute(0, 2, 3, 1).cpu()]
        path = Path(self.log_dir) / (f"{name}.gif" if step is None else f"{name}_{step}.gif")
        path.parent.mkdir(parents=True, exist_ok=True)
        # Pillow merges identical consecutive frames into one of the summed duration.
        frames[0].save(path, save_all=True, append_images=frames[1:], duration=1000 / (fps or self.fps), loop=0)

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        raise NotImplementedError("GifLogger writes videos only")

    def log_hparams(self, cfg) -> None:
        raise NotImplementedError("GifLogger writes videos only")

    def log_histogram(self, name: str, data: Sequence, **kwargs) -> None:
        raise NotImplementedError("GifLogger writes videos only")

    def __repr__(self) -> str:
        return f"GifLogger(log_dir={self.log_dir!r})"


def gif_recorder(log_dir: str | Path, tag: str, in_key=keys.PIXELS, fps: int = VIDEO_FPS) -> VideoRecorder:
    """A ``VideoRecorder`` of every frame of ``in_key`` (one env, or a batched env of one), whose
    ``dump(step=i)`` writes ``<log_dir>/<tag>_<i>.gif``. Append it to an env of
    :func:`~torchrl_dalir.envs.make_env` built with ``pixels=...``.

    Example:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_dalir import make_env
        >>> recorder = gif_recorder("videos", "reach")  # doctest: +SKIP
        >>> env = TransformedEnv(make_env("reach", pixels=VIDEO_SIZE), recorder)  # doctest: +SKIP
        >>> env.rollout(20)  # doctest: +SKIP
        >>> env.transform.dump(step=0)  # writes videos/reach_0.gif  # doctest: +SKIP
    """
    return VideoRecorder(GifLogger(log_dir, fps), tag, in_keys=[in_key], skip=1, make_grid=False)
