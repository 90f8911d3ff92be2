"""Trajectory data: collection, terminal labels, on-disk storage and training windows."""

from torchrl_dalir.data.collection import Source, collect
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
    "quality_tag",
    "trajectory_rows",
]
