"""One point cloud per task, saved as a PNG, to check camera and crop box by eye.

    python examples/paper/plot_point_clouds.py tasks=[door,pen,disassemble] out=docs/point_clouds

MetaWorld clouds are taken after ``steps`` expert steps (gripper near the object); Adroit
clouds at the first step (no expert yet).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

from torchrl_dalir import keys, make_env
from torchrl_dalir.config import parse_config
from torchrl_dalir.envs import get_task
from torchrl_dalir.envs.tasks import ADROIT
from torchrl_dalir.evaluation.plots import plot_point_cloud
from torchrl_dalir.experts import make_expert


@dataclass
class Config:
    tasks: list[str] = field(
        default_factory=lambda: ["door", "pen", "disassemble", "shelf-place", "stick-pull", "pick-place-wall"]
    )
    steps: int = 30
    seed: int = 0
    out: str = "docs/point_clouds"


def main(argv: list[str]) -> None:
    cfg: Config = parse_config(Config, argv)
    specs = [get_task(task) for task in cfg.tasks]  # an unknown name fails before the first plot
    for task, spec in zip(cfg.tasks, specs):
        env = make_env(task, seed=cfg.seed)
        policy = None if spec.suite == ADROIT else make_expert(task)
        steps = 1 if spec.suite == ADROIT else cfg.steps
        td = env.rollout(steps, policy, break_when_any_done=False)[-1]["next"] if policy else env.reset()
        path = plot_point_cloud(
            td[keys.POINT_CLOUD], f"{cfg.out}/{task}.png", title=task, crop_low=spec.crop_low, crop_high=spec.crop_high
        )
        print(f"{task}: {path}")
        env.close()


if __name__ == "__main__":
    main(sys.argv[1:])
