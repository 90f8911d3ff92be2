"""Diagnostics of the latent imagination module on held-out trajectories (the paper's Fig. 2)."""

from __future__ import annotations

import torch

from torchrl_dalir import keys
from torchrl_dalir.data import TrajectoryDataset


@torch.no_grad()
def imagination_curves(parts, dataset: TrajectoryDataset, trajectory: int, action_steps: int = 8) -> dict:
    """Along one trajectory: the scorer on ``s_t`` against the Monte-Carlo target, and the score
    of ``s_hat_t = s_{t-k} + W(s_{t-k}, a_{t-k:t})`` against the score of the true ``s_t``."""
    rows = dataset.trajectory(trajectory)
    latents = parts.encoder(rows[keys.POINT_CLOUD].clone(), rows[keys.AGENT_POS].clone())
    scores = torch.sigmoid(parts.scorer(latents))
    num_actions = len(rows) - 1
    starts = torch.arange(0, num_actions - action_steps + 1)
    actions = torch.stack([rows[keys.ACTION][s : s + action_steps] for s in starts.tolist()]) if len(starts) else None
    imagined = (
        torch.sigmoid(parts.scorer(parts.world_model.imagine(latents[starts], actions)))
        if actions is not None
        else torch.zeros(0)
    )
    return {
        "label": float(rows[keys.TERMINAL_LABEL][0]),
        "step": rows[keys.STEP].tolist(),
        "target": rows[keys.COMPLETION_TARGET].tolist(),
        "score": scores.tolist(),
        "future_step": (starts + action_steps).tolist(),
        "imagined_score": imagined.tolist(),
        "true_future_score": scores[starts + action_steps].tolist(),
    }
