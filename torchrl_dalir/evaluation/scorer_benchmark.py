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

with the policy's digest, task and chunk sizes. :func:`scorer_ladder` measures every scorer on it: out of fold
(a scorer never sees the decisions it ranks), the within-decision AUC on the decisions that split under the
collection's draw, and the offline gain, the picked candidate's mean outcome over all ``M`` draws minus the clean
candidate's, beside the honest ceiling (:func:`~torchrl_dalir.evaluation.outcome_noise.honest_ceiling`).
"""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import torch
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.data.branched import DECISION, RESET_SEED, SUCCESS
from torchrl_dalir.evaluation.candidate_outcomes import within_decision_auc
from torchrl_dalir.evaluation.outcome_noise import honest_ceiling, repeatability
from torchrl_dalir.objectives.within_state_ranking import split_decisions
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
    (:func:`~torchrl_dalir.evaluation.outcome_noise.privileged_states`)."""
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


def save_benchmark(path: str | Path, contents: dict) -> None:
    """Writes a benchmark file atomically (tensors and plain values only: it loads with ``weights_only``)."""
    buffer = io.BytesIO()
    torch.save(contents, buffer)
    atomic_write(path, buffer.getvalue())


def load_benchmark(path: str | Path) -> tuple[TensorDict, dict]:
    """A benchmark file's decisions (float32 clouds) and its description (task, digest, sizes)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no scorer benchmark at {path}: build one with examples/paper/scorer_benchmark.py")
    contents = torch.load(path, weights_only=True)
    if contents.get("format") != FORMAT:
        raise ValueError(f"{path} is a scorer benchmark of format {contents.get('format')}, not {FORMAT}")
    columns = contents.pop("rows")
    rows = TensorDict(columns, batch_size=columns[SUCCESS].shape[:1])
    rows[keys.POINT_CLOUD] = rows[keys.POINT_CLOUD].float()
    return rows, contents


def scorer_ladder(
    rows: TensorDict, sizes: dict, training: RankingTrainingConfig | None = None, folds: int = 10, scorers=SCORERS
) -> dict:
    """Every rung on one benchmark's decisions: the honest ceiling, the first draw's outcome as a score of the
    others, the clean candidate and each learned scorer of ``scorers`` (out of fold over ``folds`` groups of
    episodes). AUCs on the decisions that split under the collection's draw; gains over all decisions, judged by
    the mean over every draw."""
    training = training if training is not None else RankingTrainingConfig()
    policy = SimpleNamespace(**sizes)  # the chunk sizes are all a scorer of precomputed inputs needs of the policy
    outcomes = torch.cat([rows[SUCCESS].unsqueeze(-1), rows[REDRAWS]], -1)  # [D, K, M]
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
    return ladder
