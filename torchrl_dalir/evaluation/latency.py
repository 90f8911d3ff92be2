"""Milliseconds per decision of the base policies alone and with DALI-R (the paper's Table 5), on any device.

The models are built untrained with a preset's architectures (latency does not depend on the weights) and
time full decisions on one observation; :func:`latency_table` prints the rows beside their ratio to the
base policy alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.config import check_choice, parse_config
from torchrl_dalir.evaluation.timing import median_ms
from torchrl_dalir.modules import LatentEncoder, LatentWorldModel, PolicyConfig, TaskCompletionScorer, make_policy
from torchrl_dalir.reranking import RerankingActor
from torchrl_dalir.training import POLICY_PRESETS, WORLD_MODEL_PRESETS, WorldModelTrainingConfig
from torchrl_dalir.training.precision import PRECISIONS, autocast_dtype

# The paper's Table 5 (GPU, 32 candidates): milliseconds per decision of the base policy and DALI-R.
PAPER_TABLE5_MS = {"fm": {"base_policy": 7.83, "dalir_32": 13.62}, "dp": {"base_policy": 70.7, "dalir_32": 108.9}}


@dataclass
class LatencyConfig:
    """What :func:`measure_latency` times.

    Args:
        preset: the policy and world-model architectures (``cpu``, ``paper`` or ``smoke``).
        kinds: the base policies (``fm``, ``dp``).
        euler_steps: of the FM policy (DP keeps the preset's DDIM steps).
        candidates: DALI-R's candidates per decision, one column each.
        precisions: ``fp32``, ``bf16`` (autocast, as training's ``precision=bf16``) or ``auto``, one row each.
        num_points, action_dim, state_dim: the observation and action sizes.
        warmup, repeats: untimed calls, then the timed calls whose median is reported.
        device: where the models run (``cuda``: each timing is synchronised).
    """

    preset: str = "cpu"
    kinds: list[str] = field(default_factory=lambda: ["fm", "dp"])
    euler_steps: int = 1
    candidates: list[int] = field(default_factory=lambda: [1, 4, 8, 16, 32])
    precisions: list[str] = field(default_factory=lambda: ["fp32"])
    num_points: int = 512
    action_dim: int = 4
    state_dim: int = 4
    warmup: int = 5
    repeats: int = 30
    device: str = "cpu"

    def __post_init__(self):
        check_choice("preset", self.preset, POLICY_PRESETS)
        for precision in self.precisions:
            check_choice("precisions entry", precision, PRECISIONS)


@torch.no_grad()
def measure_latency(cfg: LatencyConfig) -> list[dict]:
    """One row per base policy and precision: the base policy's milliseconds per decision and DALI-R's at
    each number of candidates (``dalir_<n>_ms``), medians of ``cfg.repeats`` decisions in this process."""
    device = torch.device(cfg.device)
    wm = parse_config(WorldModelTrainingConfig, [f"preset={cfg.preset}"], WORLD_MODEL_PRESETS)
    model_preset = POLICY_PRESETS[cfg.preset].get("model", {})
    obs = TensorDict(
        {keys.POINT_CLOUD: torch.rand(1, 2, cfg.num_points, 3), keys.AGENT_POS: torch.rand(1, 2, cfg.state_dim)},
        [1],
        device=device,
    )
    rows = []
    for kind in cfg.kinds:
        policy_cfg = PolicyConfig(kind=kind, **model_preset)
        policy_cfg.euler_steps = cfg.euler_steps
        policy = make_policy(policy_cfg, cfg.action_dim, cfg.state_dim).to(device).eval()
        encoder = LatentEncoder.from_policy(policy).to(device)
        world_model = LatentWorldModel(
            encoder.latent_dim, cfg.action_dim, policy_cfg.action_steps, wm.wm_hidden, wm.wm_layers, wm.wm_heads
        ).to(device)
        scorer = TaskCompletionScorer(encoder.latent_dim, wm.scorer_hidden).to(device)
        for precision in cfg.precisions:
            dtype = autocast_dtype(precision, device)
            with torch.autocast(device.type, dtype=dtype or torch.bfloat16, enabled=dtype is not None):
                row = {
                    "kind": kind,
                    "precision": precision,
                    "device": str(device),
                    "steps": policy_cfg.euler_steps if kind == "fm" else policy_cfg.ddim_steps,
                    "base_policy_ms": round(median_ms(lambda: policy(obs.clone()), cfg.warmup, cfg.repeats, device), 2),
                }
                for n in cfg.candidates:
                    actor = RerankingActor(policy, encoder, world_model, scorer, num_candidates=n)
                    ms = median_ms(lambda: actor(obs.clone()), cfg.warmup, cfg.repeats, device)
                    row[f"dalir_{n}_ms"] = round(ms, 2)
            rows.append(row)
    return rows


def latency_table(rows: list[dict], candidates: list[int]) -> list[str]:
    """The rows of :func:`measure_latency` as markdown lines: a column per row, each time beside its ratio to
    the base policy alone."""
    header = "| N_cand | " + " | ".join(
        f"{r['kind'].upper()} ({r['precision']}, {r.get('device', 'cpu')}) + DALI-R ms (x base)" for r in rows
    )
    lines = [
        header + " |",
        "|" + " --- |" * (len(rows) + 1),
        "| base policy | " + " | ".join(f"{r['base_policy_ms']:.1f} (1.00)" for r in rows) + " |",
    ]
    for n in candidates:
        cells = (f"{r[f'dalir_{n}_ms']:.1f} ({r[f'dalir_{n}_ms'] / r['base_policy_ms']:.2f})" for r in rows)
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return lines
