"""The task registry: each benchmark task's simulator id, camera, crop box, step limit and robot state.

``TASKS`` holds the paper's six tasks; any other MetaWorld v3 task is available by its name
(``"reach"`` or ``"reach-v3"``) with the MetaWorld defaults. Crop boxes are world-frame xyz bounds
that keep the robot and the objects and drop the table and the background; the plots under
``docs/point_clouds/`` show what each one keeps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

METAWORLD = "metaworld"
ADROIT = "adroit"


@dataclass(frozen=True)
class TaskSpec:
    """Everything task-specific about an environment, in one place.

    Args:
        name: the task's short name (``"door"``, ``"disassemble"``, ...).
        suite: ``"metaworld"`` or ``"adroit"``.
        env_id: the simulator's environment id.
        camera: the MuJoCo camera that renders the depth image.
        crop_low, crop_high: world-frame xyz bounds of the kept workspace.
        max_steps: the episode's step limit.
        image_size: the depth image's side in pixels.
        agent_pos_dim: how many leading ``qpos`` entries (Adroit) or observation entries
            (MetaWorld: hand xyz and gripper opening) form the robot's proprioception.

    Example:
        >>> import dataclasses
        >>> spec = get_task("disassemble")
        >>> spec.suite, spec.env_id, spec.max_steps, spec.agent_pos_dim
        ('metaworld', 'disassemble-v3', 200, 4)
        >>> dataclasses.replace(spec, max_steps=80).max_steps  # a variant, e.g. for make_env(spec)
        80
    """

    name: str
    suite: str
    env_id: str
    camera: str
    crop_low: tuple[float, float, float]
    crop_high: tuple[float, float, float]
    max_steps: int
    image_size: int
    agent_pos_dim: int

    def privileged_state(self, raw_env, observation: np.ndarray) -> np.ndarray:
        """What experts read. MetaWorld: the full observation (goal included). Adroit: the
        observation followed by the simulator's ``qpos`` and ``qvel``, so an expert can rebuild
        the kinematics (Jacobians, gravity terms) from the state alone."""
        if self.suite == METAWORLD:
            return observation
        return np.concatenate([observation, raw_env.data.qpos, raw_env.data.qvel])

    def agent_pos(self, raw_env, observation: np.ndarray) -> np.ndarray:
        """Robot proprioception only: never object or goal state."""
        if self.suite == METAWORLD:
            return observation[: self.agent_pos_dim]
        return raw_env.data.qpos[: self.agent_pos_dim]


# Above z = 0.01 removes the table; below y = 0.93 removes the board at the back of the table.
_METAWORLD_CROP = dict(crop_low=(-0.50, 0.30, 0.01), crop_high=(0.50, 0.93, 0.75))
_METAWORLD_DEFAULTS = dict(suite=METAWORLD, camera="corner2", max_steps=200, image_size=160, agent_pos_dim=4)


def _metaworld(name: str) -> TaskSpec:
    return TaskSpec(name=name, env_id=f"{name}-v3", **_METAWORLD_DEFAULTS, **_METAWORLD_CROP)


#: The paper's six tasks by name (:class:`TaskSpec` each); :func:`get_task` also builds any other MetaWorld v3 task.
TASKS: dict[str, TaskSpec] = {
    "door": TaskSpec(
        name="door",
        suite=ADROIT,
        env_id="AdroitHandDoor-v1",
        camera="fixed",
        crop_low=(-0.35, -0.30, 0.01),
        crop_high=(0.50, 0.40, 0.60),
        max_steps=200,
        image_size=128,
        agent_pos_dim=28,  # arm (4) and hand (24) joints
    ),
    "pen": TaskSpec(
        name="pen",
        suite=ADROIT,
        env_id="AdroitHandPen-v1",
        camera="fixed",
        crop_low=(-0.15, -0.50, 0.12),
        crop_high=(0.30, -0.10, 0.40),
        max_steps=200,
        image_size=128,
        agent_pos_dim=24,  # hand joints
    ),
    **{name: _metaworld(name) for name in ("disassemble", "shelf-place", "stick-pull", "pick-place-wall")},
}


def metaworld_task_names() -> list[str]:
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    return sorted(name.removesuffix("-v3") for name in ALL_V3_ENVIRONMENTS)


def get_task(task: str | TaskSpec) -> TaskSpec:
    """Looks a task up by name; unknown names fail with the list of known ones."""
    if isinstance(task, TaskSpec):
        return task
    if task in TASKS:
        return TASKS[task]
    name = task.removesuffix("-v3")
    known_metaworld = metaworld_task_names()
    if name in known_metaworld:
        return _metaworld(name)
    raise KeyError(
        f"unknown task {task!r}. Benchmark tasks: {sorted(TASKS)}; "
        f"other MetaWorld v3 tasks: {[n for n in known_metaworld if n not in TASKS]}"
    )
