"""Benchmark environments with world-frame point-cloud observations."""

from torchrl_dalir.envs.make_env import make_env
from torchrl_dalir.envs.tasks import TASKS, TaskSpec, get_task

__all__ = ["TASKS", "TaskSpec", "get_task", "make_env"]
