"""The candidates' ceiling: the base policy against an oracle that executes a candidate whose
branch succeeded in the simulator, per candidate generator, on validation episodes.

    python examples/paper/candidate_ceiling.py policies=[outputs/pipeline/policies/shelf-place/fm_seed0/checkpoint.pt]
    python examples/paper/candidate_ceiling.py policies=[...] generators=[dropout,clean] num_candidates=8 episodes=20 \\
        json=docs/results/candidate_ceiling.json

A measurement, never a method (:mod:`torchrl_dalir.branching.ceiling`): it says how
much any scorer could gain with these candidates, and which generator has the headroom. Each
policy's episodes are appended to ``<out>/<task>/<run>.jsonl`` as they finish, so a killed run
resumes where it stopped, and a second command with the same settings only summarises. Prints a
markdown table; ``json`` also writes the summary with every episode's outcome.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.branching.ceiling import candidate_ceiling, summarize_ceiling
from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.config import check_at_least, parse_config
from torchrl_dalir.evaluation.calibration import TEST_SEED
from torchrl_dalir.reranking import RerankingConfig, candidate_generator
from torchrl_dalir.utils import atomic_write, provenance, weights_digest


@dataclass
class Config:
    policies: list[str] = field(
        default_factory=list
    )  # policy checkpoints, .../<task>/<policy>_seed<seed>/checkpoint.pt
    # point dropout (the paper's), re-sampling the policy's noise from the clean observation, or Gaussian point noise
    generators: list[str] = field(default_factory=lambda: ["dropout", "clean"])
    dropout: float = RerankingConfig.dropout  # point dropout's probability
    noise_std: float = RerankingConfig.noise_std  # the Gaussian noise's std, in metres
    num_candidates: int = 8  # per decision, the clean one included
    episodes: int = 20
    seed: int = 1  # evaluation seed of the validation episodes
    exhaustive: bool = False  # branch every candidate at every decision (counts the decisions that split)
    stride: int = 1  # the oracle chooses at every stride-th decision (> 1: a cheaper lower bound)
    measure: bool = True  # false: summarise the episodes measured so far, run none (a run cut short by its budget)
    out: str = "outputs/candidate_ceiling"
    json: str | None = None
    device: str = "cpu"
    progress: bool = True

    def __post_init__(self):
        if not self.policies:
            raise ValueError("name the policies: policies=[<checkpoint.pt>, ...]")
        for name in self.generators:
            self.reranking(name)  # an unknown name fails here, before any episode
        if self.seed == TEST_SEED:
            raise ValueError(
                f"seed={TEST_SEED} holds the test episodes; measure the ceiling on validation episodes (seed=1)"
            )
        check_at_least("num_candidates", self.num_candidates, 2)
        check_at_least("episodes", self.episodes, 1)
        check_at_least("stride", self.stride, 1)
        for path in self.policies:
            if not Path(path).is_file():
                raise FileNotFoundError(f"no policy checkpoint at {path}")

    def reranking(self, generator: str) -> RerankingConfig:
        return RerankingConfig(self.num_candidates, generator, self.dropout, self.noise_std)

    def strength(self, generator: str) -> float:
        return self.reranking(generator).generator_setting

    def settings(self) -> dict:
        """What an episode's outcome depends on, besides the policy (its weights digest joins it): a resumed
        file must match it."""
        return {
            "generators": {g: self.strength(g) for g in self.generators},
            "num_candidates": self.num_candidates,
            "seed": self.seed,
            "exhaustive": self.exhaustive,
            "stride": self.stride,
        }


def _run_name(path: str) -> str:
    return Path(path).parent.name  # <policy>_seed<seed>


def _read_episodes(path: Path, settings: dict) -> list[dict]:
    """The finished episodes of a resumed run (a torn last line from a kill is dropped)."""
    if not path.exists():
        return []
    lines = path.read_text().splitlines()
    header = json.loads(lines[0])
    if header != {"settings": settings}:
        raise ValueError(f"{path} was measured with {header}, not {settings}: choose another out= or delete it")
    episodes = []
    for line in lines[1:]:
        try:
            episodes.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return episodes


def measure(cfg: Config, checkpoint: str) -> dict:
    policy = load_policy(checkpoint, cfg.device)
    path = Path(cfg.out) / policy.task / f"{_run_name(checkpoint)}.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    settings = {**cfg.settings(), "policy_digest": weights_digest(policy)}  # a retrained policy starts anew
    episodes = _read_episodes(path, settings)
    if not path.exists() or len(path.read_text().splitlines()) != len(episodes) + 1:  # new, or a torn line to drop
        atomic_write(path, "".join(json.dumps(r) + "\n" for r in [{"settings": settings}, *episodes]))

    def append(record: dict) -> None:
        with path.open("a") as file:
            file.write(json.dumps(record) + "\n")

    generators = {g: candidate_generator(cfg.reranking(g)) for g in cfg.generators}
    if cfg.measure:
        episodes += candidate_ceiling(
            policy,
            policy.task,
            generators,
            episodes=cfg.episodes,
            seed=cfg.seed,
            num_candidates=cfg.num_candidates,
            exhaustive=cfg.exhaustive,
            stride=cfg.stride,
            done=[r["episode"] for r in episodes],
            on_episode=append,
            progress=cfg.progress,
            device=cfg.device,
        )
    episodes = sorted((r for r in episodes if r["episode"] < cfg.episodes), key=lambda r: r["episode"])
    return {
        "task": policy.task,
        "policy": policy.config.kind,
        "run": _run_name(checkpoint),
        "checkpoint": checkpoint,
        **summarize_ceiling(episodes),
        "episode_outcomes": episodes,
    }


def table(results: list[dict]) -> str:
    generators = list(results[0]["generators"]) if results else []
    head = "| task | policy | run | episodes | base | " + " | ".join(f"oracle: {g}" for g in generators) + " |"
    lines = [head, "|" + " --- |" * (5 + len(generators))]
    for r in results:
        cells = [
            f"{100 * e['oracle_success_rate']:.0f} % (+{e['failures_fixed']} of {e['failures']} failures)"
            for e in r["generators"].values()
        ]
        lines.append(
            f"| {r['task']} | {r['policy']} | {r['run']} | {r['episodes']} | {100 * r['base_success_rate']:.0f} % | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines)


def main(argv: list[str]) -> list[dict]:
    cfg = parse_config(Config, argv)
    results = [measure(cfg, checkpoint) for checkpoint in cfg.policies]
    print(table(results))
    if cfg.json:
        payload = {
            **provenance("examples/paper/candidate_ceiling.py", argv, cfg),
            "runs": results,
        }
        atomic_write(cfg.json, json.dumps(payload, indent=1) + "\n")
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
