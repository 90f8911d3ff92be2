"""Configuration of data collection (expert demos and mixed-quality data), with presets."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.config import check_at_least, check_choice
from torchrl_dalir.data.collection import BACKENDS, Source
from torchrl_dalir.envs.tasks import get_task


@dataclass
class CollectionConfig:
    """What ``examples/collect_data.py`` collects.

    Demos are clean expert successes (failed attempts are dropped and counted); the mixed data
    splits ``num_mixed`` trajectories evenly over the drift-noise scales of the expert (scale 0
    included), keeping successes and failures alike.
    """

    task: str = "disassemble"
    preset: str = "cpu"
    out: str = "outputs/data"
    mixed_name: str = "mixed"  # the mixed data goes to <out>/<task>/<mixed_name>
    stage: str = "all"  # demos | mixed | all
    seed: int = 0  # demos use dataset seed 2 * seed, mixed data 2 * seed + 1
    num_demos: int = 10
    num_mixed: int = 1000
    noise_scales: list[float] = field(default_factory=lambda: [0.0, 0.1, 0.15, 0.2, 0.3])
    noise_correlation: float = 0.9
    gamma: float = 0.99
    num_points: int = 512
    num_workers: int = 2  # collector workers; the data do not depend on it
    backend: str = "local"  # local (worker processes here) | ray (Ray actors; pip install "torchrl_dalir[ray]")
    ray_address: str = (
        ""  # with backend=ray: the cluster to join ("auto": the one started on this machine); "" starts a local one
    )
    chunk_size: int = 100
    progress: bool = True

    def __post_init__(self):
        get_task(self.task)  # an unknown name fails here, with the list of known ones
        check_choice("stage", self.stage, ("demos", "mixed", "all"))
        check_choice("backend", self.backend, BACKENDS)
        for name, minimum in (
            ("chunk_size", 1),
            ("num_points", 1),
            ("num_workers", 1),
            ("num_demos", 1),
            ("num_mixed", 0),
            ("seed", 0),
        ):
            check_at_least(name, getattr(self, name), minimum)
        check_at_least("the number of noise_scales", len(self.noise_scales), 1)

    def task_dir(self) -> Path:
        return Path(self.out) / self.task

    def demos_dir(self) -> Path:
        return self.task_dir() / "demos"

    def mixed_dir(self) -> Path:
        return self.task_dir() / self.mixed_name

    def collection_kwargs(self) -> dict:
        """The keywords of :func:`~torchrl_dalir.data.collect` that the demos and the mixed data share."""
        ray_init_config = {"address": self.ray_address} if self.ray_address else None
        return dict(
            gamma=self.gamma,
            num_points=self.num_points,
            num_workers=self.num_workers,
            chunk_size=self.chunk_size,
            progress=self.progress,
            backend=self.backend,
            ray_init_config=ray_init_config,
        )

    def mixed_sources(self) -> list[Source]:
        counts = [self.num_mixed // len(self.noise_scales)] * len(self.noise_scales)
        for i in range(self.num_mixed - sum(counts)):
            counts[i] += 1
        return [
            Source(f"expert_noise_{scale:g}" if scale > 0 else "expert", count, noise_scale=scale)
            for scale, count in zip(self.noise_scales, counts)
        ]


PRESETS: dict[str, dict] = {
    # The paper: 10 demos and 1000 mixed trajectories per task.
    "paper": {},
    # Sized for the whole pipeline on a 2-core CPU: fewer mixed trajectories.
    "cpu": {"num_mixed": 300},
    # Seconds, for tests: a handful of short trajectories with small clouds.
    "smoke": {
        "num_demos": 2,
        "num_mixed": 4,
        "noise_scales": [0.0, 0.3],
        "num_points": 64,
        "num_workers": 1,
        "chunk_size": 2,
    },
}
