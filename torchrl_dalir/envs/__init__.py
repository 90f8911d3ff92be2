"""Benchmark environments with world-frame point-cloud observations."""

from torchrl_dalir.envs.make_env import env_task, make_env
from torchrl_dalir.envs.tasks import TASKS, TaskSpec, get_task

__all__ = ["TASKS", "TaskSpec", "env_task", "get_task", "make_env"]
