"""Benchmark environments with world-frame point-cloud observations."""

from torchrl_dalir.envs.make_env import action_bounds, env_task, make_env
from torchrl_dalir.envs.tasks import TASKS, TaskSpec, get_task

__all__ = ["TASKS", "TaskSpec", "action_bounds", "env_task", "get_task", "make_env"]
