"""Branched outcomes: which of several chunks, executed from one simulator state, goes on to succeed.

The mixed data labels trajectories, so a scorer trained on it learns outcomes *across* states and
never sees candidates from the same state compete. Here, along base-policy episodes on data seeds,
every candidate of a decision is executed from the saved state and continued with the base policy
to the episode's end (common random numbers, as in
:mod:`~torchrl_dalir.branching.ceiling`), and each decision is stored as one row:

======================  ===============  ===============================================================
key                     shape            meaning
======================  ===============  ===============================================================
``point_cloud``         ``[To, N, 3]``   the decision's observation history
``agent_pos``           ``[To, D]``      its robot state history
``action_chunk``        ``[K, H, A]``    the candidates (0: the base policy's own chunk)
``success``             ``[K]`` bool     whether each candidate's branch succeeded by the episode's end
``steps_to_success``    ``[K]`` int      steps from the decision to that success (-1: none)
``reset_seed``          ``[]``           the episode's reset seed (a data seed)
``decision``            ``[]``           the decision's index in its episode
======================  ===============  ===============================================================

Layout and crash safety follow :mod:`~torchrl_dalir.data.storage`: ``meta.json``, one memory-mapped
shard per finished episode (renamed into place), then ``rows/`` once complete. A killed collection
resumes at its first unfinished episode and gives the same rows.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.data import ReplayBuffer, TensorStorage
from tqdm.auto import tqdm

from torchrl_dalir import keys
from torchrl_dalir.branching.simulator import base_episode, branch_decision, observation_history
from torchrl_dalir.config import check_at_least
from torchrl_dalir.data.storage import _memmap_atomically, _read_json
from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
from torchrl_dalir.envs.tasks import TaskSpec, get_task
from torchrl_dalir.objectives.within_state_ranking import split_decisions
from torchrl_dalir.reranking.candidates import candidate_generator
from torchrl_dalir.reranking.config import RerankingConfig
from torchrl_dalir.seeds import check_data_seed
from torchrl_dalir.utils import atomic_write, weights_digest

SUCCESS, STEPS_TO_SUCCESS, RESET_SEED, DECISION = "success", "steps_to_success", "reset_seed", "decision"


@dataclass
class BranchedMeta:
    """The contents of a branched dataset's ``meta.json``; ``plan()`` must match to resume."""

    task: str
    policy_digest: str
    candidates: str  # the generator's name (RerankingConfig.candidates)
    setting: float  # its dropout probability or noise std (0 for clean)
    num_candidates: int
    episodes: int
    stride: int
    seed: int
    decisions: int = 0  # only the decisions before this index (0: all)
    done_episodes: list[int] = field(default_factory=list)
    complete: bool = False

    def plan(self) -> dict:
        return {k: v for k, v in asdict(self).items() if k not in ("done_episodes", "complete")}


def _episode_rows(
    env, policy, generator, name: str, reset_seed: int, num_candidates: int, stride: int, before: int, device
) -> TensorDict:
    """Every ``stride``-th decision (before ``before``, if not 0) of the base policy's episode reset with
    ``reset_seed``, branched."""
    episode, rows = base_episode(env, policy, reset_seed, device), []
    for j in range(len(episode.decisions)):
        if j % stride or (before and j >= before):
            continue
        chunks, successes, steps = branch_decision(env, policy, episode, j, generator, name, num_candidates, device)
        cloud, agent_pos = observation_history(policy, episode.decisions[j][1], "cpu")
        rows.append(
            TensorDict(
                {
                    keys.POINT_CLOUD: cloud[0],
                    keys.AGENT_POS: agent_pos[0],
                    keys.ACTION_CHUNK: chunks.cpu(),
                    SUCCESS: torch.tensor(successes),
                    STEPS_TO_SUCCESS: torch.tensor([took if won else -1 for won, took in zip(successes, steps)]),
                    RESET_SEED: torch.tensor(reset_seed),
                    DECISION: torch.tensor(j),
                },
                [],
            )
        )
    return torch.stack(rows)


def collect_branched(
    policy,
    root: str | Path,
    reranking: RerankingConfig | None = None,
    *,
    task: str | TaskSpec | None = None,
    episodes: int = 20,
    stride: int = 2,
    decisions: int = 0,
    seed: int,
    progress: bool = True,
    device="cpu",
) -> BranchedOutcomes:
    """Branches the candidates that ``reranking`` makes (its generator and ``num_candidates``; by
    default 8 point-dropout candidates) at every ``stride``-th decision of ``episodes`` base-policy episodes on
    data seeds ``seed, seed + 1, ...`` of ``task`` (by default the policy's), and stores them under ``root`` (see
    the module docstring). With ``decisions``, only the decisions before that index are branched: the early
    ones, where a different chunk most often changes the outcome (on pick-place-wall, 4 of the 8 decisions whose
    candidates split were the first one). Resumes an unfinished collection with the same plan; refuses a
    folder that holds another plan."""
    root = Path(root)
    reranking = reranking if reranking is not None else RerankingConfig(num_candidates=8)
    num_candidates, name = reranking.num_candidates, reranking.candidates
    check_at_least("num_candidates", num_candidates, 2)
    generator = candidate_generator(reranking)
    check_at_least("episodes", episodes, 1)
    check_at_least("stride", stride, 1)
    check_at_least("decisions", decisions, 0)
    check_data_seed(seed)
    check_data_seed(seed + episodes - 1)
    spec = get_task(task if task is not None else policy.task)
    meta = BranchedMeta(
        spec.name,
        weights_digest(policy),
        name,
        reranking.generator_setting,
        num_candidates,
        episodes,
        stride,
        seed,
        decisions,
    )
    if (root / "meta.json").exists():
        stored = BranchedMeta(**_read_json(root / "meta.json"))
        if stored.plan() != meta.plan():
            raise ValueError(
                f"{root} holds branched outcomes of another plan ({stored.plan()}), not {meta.plan()}: "
                "choose another folder or delete it"
            )
        if stored.complete:
            return BranchedOutcomes.load(root)
        meta.done_episodes = stored.done_episodes
    root.mkdir(parents=True, exist_ok=True)
    atomic_write(root / "meta.json", json.dumps(asdict(meta), indent=1))
    env = PointCloudObservation(
        make_simulator(spec), spec, policy.num_points, decision_period=policy.action_steps, history=policy.obs_steps
    )
    try:
        for episode in tqdm(
            [e for e in range(episodes) if e not in meta.done_episodes],
            desc=f"branch {spec.name}",
            disable=not progress,
        ):
            rows = _episode_rows(
                env, policy, generator, name, seed + episode, num_candidates, stride, decisions, torch.device(device)
            )
            _memmap_atomically(rows, root / "episodes" / f"{episode:05d}")
            meta.done_episodes = sorted([*meta.done_episodes, episode])
            atomic_write(root / "meta.json", json.dumps(asdict(meta), indent=1))
    finally:
        env.close()
    shards = [TensorDict.load_memmap(root / "episodes" / f"{e:05d}") for e in range(episodes)]
    _memmap_atomically(torch.cat(shards), root / "rows")
    meta.complete = True
    atomic_write(root / "meta.json", json.dumps(asdict(meta), indent=1))
    shutil.rmtree(root / "episodes")
    return BranchedOutcomes.load(root)


class BranchedOutcomes:
    """A complete branched dataset: one row per decision (memory-mapped, read-only)."""

    def __init__(self, root: Path, meta: BranchedMeta, rows: TensorDict):
        self.root, self.meta, self.rows = root, meta, rows

    @classmethod
    def load(cls, root: str | Path, policy=None) -> BranchedOutcomes:
        """The complete outcomes at ``root``; with ``policy``, refuses those of another policy's candidates."""
        root = Path(root)
        if not (root / "meta.json").exists():
            raise FileNotFoundError(
                f"no branched outcomes at {root} (no meta.json): collect them with collect_branched"
            )
        meta = BranchedMeta(**_read_json(root / "meta.json"))
        if policy is not None and meta.policy_digest != weights_digest(policy):
            raise ValueError(
                f"{root} holds the candidates of another policy (weights digest {meta.policy_digest[:12]})"
            )
        if not meta.complete:
            raise ValueError(
                f"the branched outcomes at {root} are unfinished ({len(meta.done_episodes)} of {meta.episodes} "
                "episodes): run collect_branched again to resume"
            )
        return cls(root, meta, TensorDict.load_memmap(root / "rows"))

    def split_decisions(self) -> torch.Tensor:
        """Which decisions' candidates split: some, not all, went on to succeed."""
        return split_decisions(self.rows[SUCCESS])

    def replay_buffer(self, batch_size: int | None = None, sampler=None) -> ReplayBuffer:
        """A TorchRL replay buffer over the memory-mapped decisions (no copy); a sample is a batch of decisions."""
        return ReplayBuffer(storage=TensorStorage(self.rows), sampler=sampler, batch_size=batch_size)

    def __len__(self) -> int:
        return len(self.rows)

    def __repr__(self) -> str:
        return (
            f"BranchedOutcomes(task={self.meta.task!r}, decisions={len(self)}, "
            f"split={int(self.split_decisions().sum())}, "
            f"candidates={self.meta.num_candidates}, generator={self.meta.candidates!r}, root={str(self.root)!r})"
        )
