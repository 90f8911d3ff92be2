"""A scorer benchmark anyone can rerun: branched first decisions with their redraws, held in one small file.

A benchmark file holds, for ``D`` branched decisions of one policy (``K`` candidates each), what a scorer may read
and what it is judged by, and nothing that needs a simulator or the policy's weights:

======================  =======================  ===========================================================
key                     shape                    meaning
======================  =======================  ===========================================================
``point_cloud``         ``[D, To, N, 3]`` f16    the decision's observation history (float16)
``agent_pos``           ``[D, To, S_r]``         its robot state history
``policy_condition``    ``[D, C]``               the frozen policy's condition of it (what the critic reads)
``privileged_state``    ``[D, S]``               the simulator's low-dimensional state (the teacher's input)
``action_chunk``        ``[D, K, H, A]``         the candidates (0: the clean one)
``success``             ``[D, K]`` bool          each candidate's outcome under the collection's noise draw
``redraws``             ``[D, K, M - 1]``        its outcomes under ``M - 1`` further draws
``reset_seed``          ``[D]``                  the episode's reset seed (a data seed)
======================  =======================  ===========================================================

with the policy's digest, task and chunk sizes. A *distillation file* beside it (``distill/<name>.pt``) holds what
a student needs beyond it: decision states of fresh data seeds with the policy's candidates and privileged state
(:func:`distillation_states`, no continuation, so no outcome) and a copy of the policy's observation encoders to
start from (:func:`~torchrl_dalir.modules.point_cloud_critic.policy_encoders`). :func:`scorer_ladder` measures
every scorer on it: out of fold (a scorer never sees the decisions it ranks), the within-decision AUC on the
decisions that split under the collection's draw, and the offline gain, the picked candidate's mean outcome over
all ``M`` draws minus the clean candidate's, beside the honest ceiling
(:func:`~torchrl_dalir.branching.outcome_noise.honest_ceiling`).
"""

from __future__ import annotations

import io
import lzma
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from torchrl_dalir import keys
from torchrl_dalir.branching.candidate_outcomes import within_decision_auc
from torchrl_dalir.branching.outcome_noise import honest_ceiling, repeatability
from torchrl_dalir.branching.outcomes import DECISION, RESET_SEED, SUCCESS
from torchrl_dalir.branching.simulator import base_decisions, candidate_chunks, observation_history
from torchrl_dalir.config import check_at_least
from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
from torchrl_dalir.envs.tasks import get_task
from torchrl_dalir.modules.config import executed_slice
from torchrl_dalir.modules.point_cloud_critic import policy_encoders
from torchrl_dalir.objectives.within_state_ranking import split_decisions
from torchrl_dalir.reranking.candidates import candidate_generator
from torchrl_dalir.reranking.config import RerankingConfig
from torchrl_dalir.seeds import check_data_seed
from torchrl_dalir.training.distillation import DistillationConfig, train_student
from torchrl_dalir.training.ranking import (
    POLICY_CONDITION,
    SOFT_SUCCESS,
    RankingTrainingConfig,
    cross_validated_auc,
    policy_conditions,
)
from torchrl_dalir.utils import atomic_write, weights_digest

REDRAWS = "redraws"
FORMAT = 1
LZMA_MAGIC = b"\xfd7zXZ\x00"
# The learned scorers of the ladder: what each reads and learns from (RankingTrainingConfig fields).
SCORERS = {
    "critic": {"input": "state_chunk", "targets": "outcome"},
    "critic_soft": {"input": "state_chunk", "targets": "soft"},
    "teacher": {"input": "privileged_chunk", "targets": "outcome"},
    "teacher_soft": {"input": "privileged_chunk", "targets": "soft"},
}


@torch.no_grad()
def benchmark_rows(policy, rows: TensorDict, redraws: torch.Tensor, privileged_state: torch.Tensor) -> dict:
    """A benchmark file's contents from branched ``rows`` of ``policy`` (the collection's decisions), their
    ``redraws`` ``[D, K, M - 1]`` and ``privileged_state`` ``[D, S]``
    (:func:`~torchrl_dalir.branching.outcome_noise.privileged_states`)."""
    if redraws.shape[:2] != rows[SUCCESS].shape or privileged_state.shape[0] != len(rows):
        raise ValueError(
            f"redraws {tuple(redraws.shape)} and privileged_state {tuple(privileged_state.shape)} must cover the "
            f"{tuple(rows[SUCCESS].shape)} decisions x candidates of the rows"
        )
    return {
        "format": FORMAT,
        "task": policy.task,
        "policy_digest": weights_digest(policy),
        "sizes": {"obs_steps": policy.obs_steps, "action_steps": policy.action_steps, "action_dim": policy.action_dim},
        "rows": {
            keys.POINT_CLOUD: rows[keys.POINT_CLOUD].half(),
            keys.AGENT_POS: rows[keys.AGENT_POS],
            POLICY_CONDITION: policy_conditions(rows, policy),
            keys.PRIVILEGED_STATE: privileged_state,
            keys.ACTION_CHUNK: rows[keys.ACTION_CHUNK],
            SUCCESS: rows[SUCCESS].bool(),
            REDRAWS: redraws.bool(),
            RESET_SEED: rows[RESET_SEED],
            DECISION: rows[DECISION],
        },
    }


@torch.no_grad()
def distillation_states(
    policy,
    seed: int,
    states: int,
    reranking: RerankingConfig | None = None,
    progress: bool = True,
    device="cpu",
    decisions: int = 1,
) -> TensorDict:
    """The first ``decisions`` decisions of ``states`` base-policy episodes of ``policy``'s task on data seeds
    ``seed, seed + 1, ...`` (the base policy's own chunks between them, as in branching; an episode that ends
    sooner gives fewer): the observation history, the simulator's privileged state and the candidates that
    ``reranking`` makes there (by default 8 point-dropout candidates, candidate 0 the clean one), without
    continuing any. A teacher labels them; a student learns from the labels."""
    reranking = reranking if reranking is not None else RerankingConfig(num_candidates=8)
    check_data_seed(seed)
    check_data_seed(seed + states - 1)
    check_at_least("decisions", decisions, 1)
    spec, generator = get_task(policy.task), candidate_generator(reranking)
    env = PointCloudObservation(
        make_simulator(spec), spec, policy.num_points, decision_period=policy.action_steps, history=policy.obs_steps
    )
    rows = []
    try:
        for reset_seed in tqdm(
            range(seed, seed + states), desc=f"distillation states {spec.name}", disable=not progress
        ):
            for decision, observations in enumerate(base_decisions(env, policy, reset_seed, decisions, device)):
                cloud, agent_pos = observation_history(policy, observations, "cpu")
                chunks = candidate_chunks(
                    policy, generator, observations, reranking.num_candidates, reset_seed, decision,
                    reranking.candidates, device,
                )  # fmt: skip
                rows.append(
                    {
                        keys.POINT_CLOUD: cloud[0].half(),
                        keys.AGENT_POS: agent_pos[0],
                        keys.PRIVILEGED_STATE: torch.as_tensor(
                            observations[-1][keys.PRIVILEGED_STATE], dtype=torch.float32
                        ),
                        keys.ACTION_CHUNK: chunks.cpu(),
                        RESET_SEED: torch.tensor(reset_seed),
                        DECISION: torch.tensor(decision),
                    }
                )
    finally:
        env.close()
    return torch.stack([TensorDict(row, []) for row in rows])


def distillation_contents(policy, states: TensorDict) -> dict:
    """A distillation file's contents: ``states`` (:func:`distillation_states`) and ``policy``'s encoders. Only
    what a scorer reads of the candidates is kept, their executed actions
    (:func:`~torchrl_dalir.modules.config.executed_slice`), in float16; when every state is a first decision,
    whose history repeats its one observation, one frame is kept (:func:`load_distillation` restores both).
    Saved with ``compress=True`` (:func:`save_benchmark`): 0.8-2.3 MiB per 1000 MetaWorld first decisions of 8
    candidates, 2.4-3.6 MiB on Adroit."""
    history, horizon = states[keys.POINT_CLOUD].shape[1], states[keys.ACTION_CHUNK].shape[2]
    executed = executed_slice(policy.obs_steps, policy.action_steps)
    columns = states.to_dict()
    if all((states[key] == states[key][:, :1]).all() for key in (keys.POINT_CLOUD, keys.AGENT_POS)):
        for key in (keys.POINT_CLOUD, keys.AGENT_POS):
            columns[key] = columns[key][:, :1].clone()  # a view would save the whole history
    columns[keys.ACTION_CHUNK] = columns[keys.ACTION_CHUNK][:, :, executed].half().clone()
    return {
        "format": FORMAT,
        "task": policy.task,
        "policy_digest": weights_digest(policy),
        "encoders": policy_encoders(policy),
        "history": history,
        "horizon": horizon,
        "executed": [executed.start, executed.stop],
        "rows": columns,
    }


def load_distillation(path: str | Path) -> tuple[TensorDict, dict]:
    """A distillation file's states (float32 clouds and candidates, the history's frame repeated) and its
    description (task, digest, the policy's encoders). A file that kept only the executed actions loads whole
    chunks whose other entries are NaN: no scorer reads them, and any computation that did would show it."""
    rows, info = load_benchmark(path)
    for key in (keys.POINT_CLOUD, keys.AGENT_POS):
        rows[key] = rows[key].repeat_interleave(info.get("history", rows[key].shape[1]) // rows[key].shape[1], 1)
    actions = rows[keys.ACTION_CHUNK].float()
    if "executed" in info:
        start, stop = info["executed"]
        chunks = actions.new_full((*actions.shape[:2], info["horizon"], actions.shape[-1]), float("nan"))
        chunks[:, :, start:stop] = actions
        actions = chunks
    rows[keys.ACTION_CHUNK] = actions
    return rows, info


def save_benchmark(path: str | Path, contents: dict, compress: bool = False) -> None:
    """Writes a benchmark file atomically (tensors and plain values only: it loads with ``weights_only``),
    ``compress``-ed with LZMA (a float16 point cloud of a few objects shrinks many times over)."""
    buffer = io.BytesIO()
    torch.save(contents, buffer)
    data = buffer.getvalue()
    atomic_write(path, lzma.compress(data) if compress else data)


def load_benchmark(path: str | Path) -> tuple[TensorDict, dict]:
    """A benchmark file's decisions (float32 clouds) and its description (task, digest, sizes)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no scorer benchmark at {path}: build one with examples/paper/scorer_benchmark.py")
    data = path.read_bytes()
    if data.startswith(LZMA_MAGIC):
        data = lzma.decompress(data)
    contents = torch.load(io.BytesIO(data), weights_only=True)
    if contents.get("format") != FORMAT:
        raise ValueError(f"{path} is a scorer benchmark of format {contents.get('format')}, not {FORMAT}")
    columns = contents.pop("rows")
    rows = TensorDict(columns, batch_size=columns[RESET_SEED].shape[:1])
    rows[keys.POINT_CLOUD] = rows[keys.POINT_CLOUD].float()
    return rows, contents


def all_draws(rows: TensorDict) -> torch.Tensor:
    """Every candidate's outcomes ``[D, K, M]`` of a benchmark's decisions: the collection's draw, then the redraws."""
    return torch.cat([rows[SUCCESS].unsqueeze(-1), rows[REDRAWS]], -1)


# what a privileged teacher reads and is judged by: the keys every run of a task shares
TEACHER_KEYS = (keys.PRIVILEGED_STATE, keys.ACTION_CHUNK, SUCCESS, REDRAWS, RESET_SEED)


def teacher_rows(path: str | Path) -> tuple[TensorDict, dict]:
    """A benchmark file's decisions as a privileged teacher reads them (:data:`TEACHER_KEYS`, with each
    candidate's chance over the draws as ``soft_success``) and the file's info."""
    rows, info = load_benchmark(path)
    rows = rows.select(*TEACHER_KEYS)
    return rows.set(SOFT_SUCCESS, all_draws(rows).float().mean(-1)), info


def scorer_ladder(
    rows: TensorDict,
    sizes: dict,
    training: RankingTrainingConfig | None = None,
    folds: int = 10,
    scorers=SCORERS,
    distill: tuple[TensorDict, dict] | None = None,
    distillation: DistillationConfig | None = None,
) -> dict:
    """Every rung on one benchmark's decisions: the honest ceiling, the first draw's outcome as a score of the
    others, the clean candidate and each learned scorer of ``scorers`` (out of fold over ``folds`` groups of
    episodes), and with ``distill`` (:func:`load_distillation`) the distilled student (``distillation``; its
    teacher and student trained again in every fold). AUCs on the decisions that split under the collection's
    draw; gains over all decisions, judged by the mean over every draw."""
    training = training if training is not None else RankingTrainingConfig()
    policy = SimpleNamespace(**sizes)  # the chunk sizes are all a scorer of precomputed inputs needs of the policy
    outcomes = all_draws(rows)  # [D, K, M]
    chance = outcomes.float().mean(-1)
    rows = rows.clone(False).set(SOFT_SUCCESS, chance)
    clean = torch.zeros(chance.shape)
    clean[:, 0] = 1  # the base policy's own chunk first, the others tied
    first = repeatability(rows[SUCCESS], rows[REDRAWS][..., 0])
    ladder = {
        "decisions": len(rows),
        "split_decisions": int(split_decisions(rows[SUCCESS]).sum()),
        "draws": outcomes.shape[-1],
        "honest_ceiling": honest_ceiling(outcomes),
        "first_outcome": {"auc": first["auc_of_first_draw"]},  # the stored draw scoring the first redraw
        "clean": {"auc": within_decision_auc(clean.tolist(), rows[SUCCESS].tolist()), "gain": 0.0},
    }
    for name, settings in scorers.items():
        cv = cross_validated_auc(rows, policy, replace(training, **settings), folds=folds, judge=chance)
        ladder[name] = {"auc": cv["auc"], "gain": cv["pick_success"] - cv["clean_success"], **settings}
    if distill is not None:
        states, info = distill
        distillation = distillation if distillation is not None else DistillationConfig()
        cv = cross_validated_auc(
            rows, policy, distillation, folds, chance, train=train_student, distill=states, encoders=info["encoders"]
        )
        ladder["student"] = {"auc": cv["auc"], "gain": cv["pick_success"] - cv["clean_success"], "states": len(states)}
    return ladder
