"""Trajectory data: collection, DP3 zarr import, terminal labels, on-disk storage and training windows."""

from torchrl_dalir.data.collection import Source, collect
from torchrl_dalir.data.dp3_zarr import import_dp3_zarr, write_dp3_zarr
from torchrl_dalir.data.labels import (
    TerminalLabelTransform,
    completion_targets,
    dense_reward_targets,
    quality_tag,
    trajectory_rows,
)
from torchrl_dalir.data.storage import DatasetMeta, DatasetWriter, TrajectoryDataset

__all__ = [
    "DatasetMeta",
    "DatasetWriter",
    "Source",
    "TerminalLabelTransform",
    "TrajectoryDataset",
    "collect",
    "completion_targets",
    "dense_reward_targets",
    "import_dp3_zarr",
    "quality_tag",
    "trajectory_rows",
    "write_dp3_zarr",
]
