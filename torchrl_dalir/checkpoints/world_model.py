"""World-model checkpoints: DALI-R's latent imagination module as saved, and loading it back.

A world-model checkpoint holds the latent encoder (with its architecture, ``encoder_args``), the
world model, the state scorer and the scorer ensemble trained on top of one frozen policy (this
library's or any :class:`~torchrl_dalir.modules.ChunkPolicy`, with a digest of its weights),
the selection rule (the paper's arg-max until calibration stores another) and the training
run's held-out metrics. :func:`load_world_model` returns it as a :class:`WorldModelCheckpoint`.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

from torchrl_dalir.checkpoints.files import check_entries, load_checkpoint, load_weights, save_checkpoint
from torchrl_dalir.modules.config import PolicyConfig
from torchrl_dalir.modules.policies import make_policy
from torchrl_dalir.modules.policy_interface import ChunkPolicy
from torchrl_dalir.modules.world_model import LatentEncoder, LatentWorldModel, ScorerEnsemble, TaskCompletionScorer
from torchrl_dalir.selection_config import SelectionConfig
from torchrl_dalir.utils import weights_digest

#: What a world-model checkpoint must hold to be loaded (the scorer ensemble is optional: older ones have none).
WORLD_MODEL_ENTRIES = (
    "task",
    "policy_config",
    "action_dim",
    "state_dim",
    "world_model_args",
    "scorer_hidden",
    "encoder_state",
    "scorer_state",
    "world_model_state",
    "metrics",
    "policy_checkpoint",
    "held_out_trajectories",
)


@dataclass
class WorldModelCheckpoint:
    """What a world-model checkpoint holds, loaded (:func:`load_world_model`), its modules in eval mode.

    Args:
        task: the task it was trained on.
        encoder: the latent encoder (a copy of the policy's observation encoders, fine-tuned or frozen).
        world_model: imagines the latent after a chunk's executed actions.
        scorer: the task-completion scorer of a latent.
        ensemble: the scorer ensemble trained on imagined latents (``None`` in checkpoints written
            before version 0.2.0).
        selection: the selection rule (the calibrated one, or the paper's arg-max).
        calibration: the calibration record behind ``selection`` (``None`` until calibrated).
        metrics: the training run's held-out metrics.
        policy_checkpoint: the path of the policy it was trained on top of, as given to training (for a
            policy object without a ``checkpoint``, its class and the start of its weights' digest).
        policy_digest: the digest of that policy's weights (``None`` in older checkpoints).
        held_out_trajectories: the mixed data's trajectories held out of training.

    Example:
        >>> parts = load_world_model("outputs/world_models/disassemble/seed0_frozen/world_model.pt")  # doctest: +SKIP
        >>> parts.selection.name, parts.metrics["wm_mse"] < parts.metrics["no_change_mse"]  # doctest: +SKIP
        ('argmax(state)', True)
    """

    task: str
    encoder: LatentEncoder
    world_model: LatentWorldModel
    scorer: TaskCompletionScorer
    ensemble: ScorerEnsemble | None
    selection: SelectionConfig
    calibration: dict | None
    metrics: dict
    policy_checkpoint: str
    policy_digest: str | None
    held_out_trajectories: list[int]


def save_world_model(
    path: str | Path,
    *,
    policy: ChunkPolicy,
    policy_checkpoint: str | Path,
    encoder: LatentEncoder,
    scorer: TaskCompletionScorer,
    world_model: LatentWorldModel,
    ensemble: ScorerEnsemble,
    world_model_args: dict,
    scorer_hidden: int,
    ensemble_args: dict,
    held_out_trajectories: list[int],
    metrics: dict,
    encoder_mode: str,
    config: dict,
    task: str | None = None,
) -> None:
    """Writes a world-model checkpoint (atomically) with the paper's arg-max as its selection rule
    until calibration stores another (:func:`store_selection`).

    Args:
        path: the checkpoint file.
        policy: the frozen policy it was trained on top of (its task, architecture and weights' digest are
            stored): a :class:`~torchrl_dalir.modules.ChunkPolicy3D` or any other
            :class:`~torchrl_dalir.modules.ChunkPolicy` (its digest is that of its ``state_dict``).
        policy_checkpoint: the file that policy was loaded from (or a description of a policy object).
        encoder, scorer, world_model, ensemble: the trained modules (on the CPU).
        world_model_args, scorer_hidden, ensemble_args: the modules' constructor arguments.
        held_out_trajectories: the mixed data's trajectories held out of training.
        metrics: held-out metrics.
        encoder_mode: ``"finetune"`` or ``"frozen"``.
        config: the training configuration, stored for the record.
        task: the task it was trained on (default: the policy's ``task``, which a policy of your own may lack).
    """
    from torchrl_dalir import __version__

    if task is None:
        if not hasattr(policy, "task"):
            raise ValueError(f"{type(policy).__name__} names no task: pass save_world_model(..., task=...)")
        task = policy.task
    save_checkpoint(
        path,
        {
            "kind": "world_model",
            "task": task,
            "config": config,
            "policy_checkpoint": str(policy_checkpoint),
            "policy_digest": weights_digest(policy),  # which policy's weights it was trained on (see check_trained_on)
            "encoder_mode": encoder_mode,
            "policy_config": asdict(policy.config)
            if isinstance(getattr(policy, "config", None), PolicyConfig)
            else None,
            "encoder_args": encoder.architecture(),  # rebuilds the encoder without the policy's configuration
            "action_dim": policy.action_dim,
            "state_dim": encoder.architecture()["state_dim"],
            "world_model_args": world_model_args,
            "scorer_hidden": scorer_hidden,
            "encoder_state": encoder.state_dict(),
            "scorer_state": scorer.state_dict(),
            "world_model_state": world_model.state_dict(),
            "ensemble_args": ensemble_args,
            "ensemble_state": ensemble.state_dict(),
            "selection": SelectionConfig().to_dict(),  # the paper's arg-max until calibrated
            "held_out_trajectories": held_out_trajectories,
            "metrics": metrics,
            "library_version": __version__,
        },
    )


def check_trained_on(state: dict, policy: ChunkPolicy, path: str | Path) -> None:
    """Refuses the world model of a loaded checkpoint ``state`` (read from ``path``) for a policy it
    was not trained on top of: another task (if the policy names its ``task``), or other weights than
    those whose digest it recorded (latents of other encoders and chunks of another sampler would be
    scored). A checkpoint written before digests were recorded is accepted with a warning."""
    checkpoint = getattr(policy, "checkpoint", None)
    if hasattr(policy, "task") and state["task"] != policy.task:
        raise ValueError(f"the world model at {path} is for task {state['task']!r}; the policy is for {policy.task!r}")
    recorded, source = state.get("policy_digest"), f"at {checkpoint}" if checkpoint else "given"
    if recorded is None:
        warnings.warn(
            f"{path} does not record which policy it was trained on (an older checkpoint): it is not checked against "
            f"the policy {source}. Train the world model again to record it",
            stacklevel=2,
        )
        return
    actual = weights_digest(policy)
    if actual != recorded:
        raise ValueError(
            f"the world model at {path} was trained on top of the policy at {state['policy_checkpoint']}, "
            f"not on the policy {source}, whose weights differ (digest {actual[:12]} instead of {recorded[:12]}): "
            "pass the policy it was trained on, or train a world model on this one "
            "(examples/train_world_model.py policy_checkpoint=...)"
        )


def load_world_model(path: str | Path, device="cpu", policy: ChunkPolicy | None = None) -> WorldModelCheckpoint:
    """Loads a world-model checkpoint's modules and records.

    Args:
        path: a world-model checkpoint (``train_world_model``'s ``world_model.pt``).
        device: where its modules run.
        policy: if given, a world model not trained on top of it is refused (:func:`check_trained_on`).
    """
    state = load_checkpoint(path, "world_model", WORLD_MODEL_ENTRIES)
    if policy is not None:
        check_trained_on(state, policy, path)
    if (
        state["policy_config"] is not None
    ):  # the policy's architecture (as loading always built it: the same draws from torch's generator)
        encoder = LatentEncoder.from_policy(
            make_policy(PolicyConfig(**state["policy_config"]), state["action_dim"], state["state_dim"])
        )
    else:  # a policy of another design (a ChunkPolicy): the encoder's own architecture
        check_entries(state, path, ("encoder_args",), "world_model checkpoint")
        encoder = LatentEncoder.fresh(**state["encoder_args"])
    load_weights(encoder, state, "encoder_state", path)
    world_model = LatentWorldModel(**state["world_model_args"])
    load_weights(world_model, state, "world_model_state", path)
    scorer = TaskCompletionScorer(encoder.latent_dim, state["scorer_hidden"])
    load_weights(scorer, state, "scorer_state", path)
    ensemble = None  # absent from checkpoints written before version 0.2.0
    if "ensemble_state" in state:
        check_entries(state, path, ("ensemble_args",), "world_model checkpoint")
        ensemble = ScorerEnsemble(**state["ensemble_args"])
        load_weights(ensemble, state, "ensemble_state", path)
        ensemble = ensemble.to(device).eval()
    return WorldModelCheckpoint(
        task=state["task"],
        encoder=encoder.to(device).eval(),
        world_model=world_model.to(device).eval(),
        scorer=scorer.to(device).eval(),
        ensemble=ensemble,
        selection=SelectionConfig.stored_in(state),
        calibration=state.get("calibration"),
        metrics=state["metrics"],
        policy_checkpoint=state["policy_checkpoint"],
        policy_digest=state.get("policy_digest"),
        held_out_trajectories=state["held_out_trajectories"],
    )


def store_selection(world_model_path: str | Path, selection: SelectionConfig, calibration: dict | None = None) -> None:
    """Writes ``selection`` (and the calibration record behind it) into a world-model checkpoint, atomically.

    Args:
        world_model_path: the checkpoint, rewritten in place.
        selection: the rule :meth:`RerankingActor.from_checkpoints
            <torchrl_dalir.reranking.RerankingActor.from_checkpoints>` will use with no argument.
        calibration: the record of the calibration that chose it.
    """
    state = load_checkpoint(world_model_path, "world_model")
    if selection.scorer == "ensemble" and "ensemble_state" not in state:
        raise ValueError(f"{world_model_path} has no scorer ensemble for {selection.name}")
    state["selection"], state["calibration"] = selection.to_dict(), calibration
    save_checkpoint(world_model_path, state)
