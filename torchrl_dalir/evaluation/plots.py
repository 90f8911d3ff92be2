"""Plots a person would rather look at than read."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_point_cloud(cloud, path: str | Path, title: str = "", crop_low=None, crop_high=None) -> Path:
    """Saves a 3D scatter (coloured by height) and a top view of one ``[N, 3]`` world-frame cloud."""
    cloud = np.asarray(cloud)
    fig = plt.figure(figsize=(8, 3.6), dpi=80)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    ax.scatter(cloud[:, 0], cloud[:, 1], cloud[:, 2], s=3, c=cloud[:, 2], cmap="viridis")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.view_init(elev=25, azim=-60)
    top = fig.add_subplot(1, 2, 2)
    top.scatter(cloud[:, 0], cloud[:, 1], s=3, c=cloud[:, 2], cmap="viridis")
    top.set_aspect("equal")
    top.set_xlabel("x")
    top.set_ylabel("y")
    top.set_title("top view")
    if crop_low is not None and crop_high is not None:
        for a in (ax,):
            a.set_xlim(crop_low[0], crop_high[0])
            a.set_ylim(crop_low[1], crop_high[1])
            a.set_zlim(crop_low[2], crop_high[2])
        top.set_xlim(crop_low[0], crop_high[0])
        top.set_ylim(crop_low[1], crop_high[1])
    fig.suptitle(f"{title} ({len(np.unique(cloud, axis=0))} distinct of {len(cloud)} points)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
