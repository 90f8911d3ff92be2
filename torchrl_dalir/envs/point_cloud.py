"""Depth image -> world-frame point cloud: unproject, crop to the workspace, farthest-point sample.

MuJoCo renders metric depth from a named camera; every pixel is lifted into the world frame with
the camera's pose and field of view, background pixels (which land on the far plane) and the
table are removed by the task's crop box, and farthest-point sampling keeps a fixed number of
points. Farthest-point sampling uses ``fpsample`` (a C++ bucket FPS): numpy or torch loops cost
15-60x more per step on a CPU.
"""

from __future__ import annotations

import atexit
import importlib
import os
import weakref

import fpsample
import mujoco
import numpy as np

_OPEN_CAMERAS: weakref.WeakSet = weakref.WeakSet()


def _close_open_cameras() -> None:
    for camera in list(_OPEN_CAMERAS):
        camera.close()


def _apply_requested_gl_backend() -> None:
    """MuJoCo picks its GL backend once, when first imported (TorchRL imports it early); if
    ``MUJOCO_GL`` asks for a headless backend that was not picked, switch to it now."""
    from mujoco import gl_context

    backend = os.environ.get("MUJOCO_GL", "").lower().strip()
    if backend in ("egl", "osmesa"):
        module = importlib.import_module(f"mujoco.{backend}")
        gl_context.GLContext = module.GLContext


def _track(camera) -> None:
    # MuJoCo terminates its EGL display at exit (registered with its first context): close the
    # cameras' contexts before that, not in garbage collection after it, which raises EGL errors.
    if not _OPEN_CAMERAS:
        atexit.unregister(_close_open_cameras)
        atexit.register(_close_open_cameras)
    _OPEN_CAMERAS.add(camera)


def make_renderer(model: mujoco.MjModel, image_size: int) -> mujoco.Renderer:
    """An offscreen renderer of square ``image_size`` images, on the requested GL backend; fails
    with what to install when there is no offscreen GL."""
    try:
        _apply_requested_gl_backend()
        return mujoco.Renderer(model, image_size, image_size)
    except ValueError:  # larger than the model's offscreen buffer: MuJoCo's message says so
        raise
    except Exception as error:
        raise RuntimeError(
            "MuJoCo could not create an offscreen renderer. With MUJOCO_GL=egl (the default that "
            "torchrl_dalir sets) install the Debian packages libegl1 and libgl1-mesa-dri."
        ) from error


class _Camera:
    """One named MuJoCo camera with its own offscreen renderer, closed before MuJoCo's EGL display."""

    def __init__(self, model: mujoco.MjModel, camera: str, size: int):
        self.cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if self.cam_id < 0:
            names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
            raise ValueError(f"camera {camera!r} is not in the model; it has {names}")
        self.camera = camera
        self.renderer = make_renderer(model, size)
        _track(self)

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None


class RGBCamera(_Camera):
    """Renders RGB images ``[size, size, 3]`` (uint8) from one MuJoCo camera, for videos, with the
    world's up towards the top: the image of a camera mounted upside down (MetaWorld's ``corner2``)
    is turned half a turn.

    Create it inside the process that uses it, like :class:`DepthPointCloudCamera`.

    Args:
        model: the ``mujoco.MjModel`` to render.
        camera: the camera's name in the model.
        size: the square image's side, in pixels (at most the model's offscreen buffer size).
    """

    def __call__(self, data: mujoco.MjData) -> np.ndarray:
        self.renderer.update_scene(data, camera=self.camera)
        image = self.renderer.render()
        up = data.cam_xmat[self.cam_id].reshape(3, 3)[:, 1]  # the camera's up axis in the world frame
        return np.ascontiguousarray(image[::-1, ::-1]) if up[2] < 0 else image


class DepthPointCloudCamera(_Camera):
    """Renders a cropped, farthest-point-sampled point cloud from one MuJoCo camera.

    Create it inside the process that uses it: an EGL rendering context does not cross processes.

    Args:
        model: the ``mujoco.MjModel`` to render.
        camera: the camera's name in the model.
        crop_low, crop_high: world-frame xyz bounds of the workspace box.
        num_points: points kept by farthest-point sampling.
        image_size: square depth-image side, in pixels.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        camera: str,
        crop_low,
        crop_high,
        num_points: int = 512,
        image_size: int = 128,
    ):
        super().__init__(model, camera, image_size)
        self.crop_low = np.asarray(crop_low, dtype=np.float32)
        self.crop_high = np.asarray(crop_high, dtype=np.float32)
        self.num_points = num_points
        self.points_in_crop: int | None = None  # set by each rendering
        self.renderer.enable_depth_rendering()
        # Pixel rays in the camera frame (MuJoCo cameras look along -z, with y up).
        focal = 0.5 * image_size / np.tan(np.deg2rad(model.cam_fovy[self.cam_id]) / 2)
        pix = np.arange(image_size, dtype=np.float32) + 0.5 - image_size / 2
        u, v = np.meshgrid(pix, pix)  # u: column offset, v: row offset (rows go down)
        self._rays = np.stack([u / focal, -v / focal, -np.ones_like(u)], axis=-1).reshape(-1, 3)

    def __call__(self, data: mujoco.MjData) -> np.ndarray:
        """Returns a ``[num_points, 3]`` float32 cloud in the world frame."""
        self.renderer.update_scene(data, camera=self.camera)
        depth = self.renderer.render().reshape(-1, 1)
        points_cam = self._rays * depth
        rotation = data.cam_xmat[self.cam_id].reshape(3, 3)
        points = points_cam @ rotation.T + data.cam_xpos[self.cam_id]
        points = points.astype(np.float32)
        inside = np.all((points >= self.crop_low) & (points <= self.crop_high), axis=1)
        self.points_in_crop = int(inside.sum())  # the distinct points available (one per pixel)
        return farthest_point_sample(points[inside], self.num_points)


def farthest_point_sample(points: np.ndarray, num_points: int) -> np.ndarray:
    """Farthest-point samples ``num_points`` rows of ``points`` (deterministic: starts at row 0).

    A cloud with fewer points than asked for (an object that left the crop box, say) is padded by
    repeating points, so the output shape never changes; an empty cloud is an error.
    """
    n = len(points)
    if n == 0:
        raise RuntimeError("no point of the depth image lies inside the crop box: check the camera and crop box")
    if n <= num_points:
        return points[np.arange(num_points) % n]
    index = fpsample.bucket_fps_kdline_sampling(points, num_points, h=5, start_idx=0)
    return points[index]
