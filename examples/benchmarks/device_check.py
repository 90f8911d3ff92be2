"""Does the library run on an accelerator, how fast, and does it decide as on the CPU? One command, one JSON.

    python examples/benchmarks/device_check.py device=cuda          # one GPU: under 8 minutes
    python examples/benchmarks/device_check.py preset=smoke device=cpu out=/tmp/check   # the suite's version

Three parts, each recorded even when another fails (a failure's traceback goes into the JSON and the command
exits non-zero at the end, so one run on a borrowed GPU finds every problem):

1. ``main_job``: the smoke main job (:func:`torchrl_dalir.pipeline.run_pipeline`, ``preset=smoke``) with
   ``device=<device>``, every stage (the ``smoke`` check stops after the world model), and each stage's
   seconds. A finished job in ``out`` is not run again.
2. ``latency``: the paper's Table 5 on ``device``: FM and DP alone and with DALI-R at 1-32 candidates, for
   each architecture preset and precision (:func:`torchrl_dalir.evaluation.latency.measure_latency`;
   CUDA is synchronised around each timing), beside the paper's GPU numbers.
3. ``agreement``: the main job's trained policy and world model, loaded on the CPU and on ``device``, propose
   and score the candidates of the same ``decisions`` observations (the demos' frames; the actors' noise
   comes from the same CPU generator; fp32 without TF32). The chunks and scores must match within ``tolerance`` and the
   arg-max candidates agree, except where the CPU's two best scores lie within ``tolerance`` of each other.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchrl_dalir import RerankingActor, keys
from torchrl_dalir.config import parse_config
from torchrl_dalir.data.storage import TrajectoryDataset
from torchrl_dalir.evaluation.latency import PAPER_TABLE5_MS, LatencyConfig, latency_table, measure_latency
from torchrl_dalir.pipeline import PRESETS as PIPELINE_PRESETS
from torchrl_dalir.pipeline import PipelineConfig, run_pipeline
from torchrl_dalir.reranking import SelectionConfig
from torchrl_dalir.utils import atomic_write, provenance

QUIET = ["collection.progress=false", "policy_training.progress=false", "world_model.progress=false"]


@dataclass
class Config:
    preset: str = "paper"
    device: str = "cuda"
    task: str = "disassemble"  # of the smoke main job
    pipeline_overrides: list[str] = field(default_factory=lambda: list(QUIET))
    architectures: list[str] = field(default_factory=lambda: ["cpu", "paper"])  # the latency table's presets
    kinds: list[str] = field(default_factory=lambda: ["fm", "dp"])
    candidates: list[int] = field(default_factory=lambda: [1, 4, 8, 16, 32])
    precisions: list[str] = field(default_factory=lambda: ["fp32", "bf16"])
    warmup: int = 5
    repeats: int = 30
    decisions: int = 16  # observations of the agreement check
    num_candidates: int = 32  # per decision of the agreement check
    tolerance: float = 1e-3  # largest difference of an action or a score (probability) between the devices
    out: str = "outputs/device_check"
    json: str | None = None  # default: <out>/device_check.json

    def __post_init__(self):
        device = torch.device(self.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise RuntimeError(
                f"device={self.device} but torch {torch.__version__} sees no CUDA device "
                f"(torch.version.cuda={torch.version.cuda}): install a CUDA build of torch, or pass device=cpu"
            )


PRESETS = {
    "paper": {},
    "smoke": {
        "task": "reach",
        "pipeline_overrides": [*QUIET, "until=world_model"],  # the stages the agreement needs
        "architectures": ["smoke"],
        "candidates": [1, 2],
        "precisions": ["fp32"],
        "warmup": 0,
        "repeats": 1,
        "decisions": 3,
        "num_candidates": 4,
    },
}


def main_job(cfg: Config) -> dict:
    """The smoke main job on ``cfg.device``; returns its seconds per stage and its checkpoints."""
    args = ["preset=smoke", f"task={cfg.task}", f"device={cfg.device}", f"out={Path(cfg.out) / 'pipeline'}"]
    job = parse_config(PipelineConfig, args + cfg.pipeline_overrides, PIPELINE_PRESETS)
    start = time.perf_counter()
    results = run_pipeline(job)
    stages = [json.loads(line) for line in job.stage_log_path().read_text().splitlines() if line.strip()]
    return {
        "seconds": round(time.perf_counter() - start, 1),
        "stage_seconds": {line["stage"]: line["seconds"] for line in stages},
        "results": str(results),
        "policy": str(job.policy_training.run_dir() / "checkpoint.pt"),
        "world_model": str(job.world_model.run_dir() / "world_model.pt"),
        "demos": str(job.collection.demos_dir()),
    }


def latency(cfg: Config) -> dict:
    """The latency table on ``cfg.device`` for each architecture preset, beside the paper's Table 5."""
    rows = []
    for architecture in cfg.architectures:
        timing = LatencyConfig(
            preset=architecture,
            kinds=cfg.kinds,
            candidates=cfg.candidates,
            precisions=cfg.precisions,
            warmup=cfg.warmup,
            repeats=cfg.repeats,
            device=cfg.device,
        )
        for row in measure_latency(timing):
            rows.append({"architecture": architecture, **row})
            print(json.dumps(rows[-1]), flush=True)
    table = latency_table(rows, cfg.candidates)
    print("\n".join(table))
    return {"rows": rows, "table": table, "paper_table5_ms": PAPER_TABLE5_MS}


@contextlib.contextmanager
def full_fp32():
    """CUDA's fp32 products in full precision (no TF32: cuDNN convolutions use it by default), restored after:
    the agreement checks the arithmetic, not a speed setting."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@torch.no_grad()
@full_fp32()
def agreement(cfg: Config, job: dict) -> dict:
    """The same decisions proposed and scored on the CPU and on ``cfg.device`` from the main job's weights (fp32
    without TF32 on CUDA)."""
    proposals = {}
    for device in ("cpu", cfg.device):
        actor = RerankingActor.from_checkpoints(
            job["policy"], job["world_model"], device, num_candidates=cfg.num_candidates, selection=SelectionConfig()
        )
        frames = TrajectoryDataset.load(job["demos"], num_points=actor.policy.num_points).rows
        index = torch.linspace(0, len(frames) - 1, cfg.decisions).long()  # spread over the demos
        # a frame repeated as its own history, as at an episode's first step
        cloud = frames[keys.POINT_CLOUD][index].unsqueeze(1).expand(-1, actor.policy.obs_steps, -1, -1)
        agent_pos = frames[keys.AGENT_POS][index].unsqueeze(1).expand(-1, actor.policy.obs_steps, -1)
        chunks, scores = actor.propose(cloud.to(device).contiguous(), agent_pos.to(device).contiguous())
        proposals[device] = (chunks.cpu(), scores.cpu())
    (cpu_chunks, cpu_scores), (dev_chunks, dev_scores) = proposals["cpu"], proposals[cfg.device]
    top2 = cpu_scores.topk(2, dim=-1).values
    clear = (top2[:, 0] - top2[:, 1]) > cfg.tolerance  # decisions without a near tie on the CPU
    same_choice = cpu_scores.argmax(-1) == dev_scores.argmax(-1)
    result = {
        "decisions": cfg.decisions,
        "num_candidates": cfg.num_candidates,
        "tolerance": cfg.tolerance,
        "max_action_difference": float((cpu_chunks - dev_chunks).abs().max()),
        "max_score_difference": float((cpu_scores - dev_scores).abs().max()),
        "same_choice": int(same_choice.sum()),
        "clear_decisions": int(clear.sum()),
        "same_choice_of_clear": int(same_choice[clear].sum()),
    }
    result["passed"] = (
        result["max_action_difference"] <= cfg.tolerance
        and result["max_score_difference"] <= cfg.tolerance
        and result["same_choice_of_clear"] == result["clear_decisions"]
    )
    return result


def environment(device: str) -> dict:
    info = {"torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(), "device": device}
    if torch.device(device).type == "cuda":
        info.update(
            gpu=torch.cuda.get_device_name(device),
            cuda=torch.version.cuda,
            cudnn_allow_tf32=torch.backends.cudnn.allow_tf32,
            matmul_allow_tf32=torch.backends.cuda.matmul.allow_tf32,
        )
    return info


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv, PRESETS)
    path = Path(cfg.json) if cfg.json else Path(cfg.out) / "device_check.json"
    payload = {**provenance("examples/benchmarks/device_check.py", argv, cfg), "environment": environment(cfg.device)}
    failed = []

    def part(name, measure):
        print(f"[device_check] {name} on {cfg.device}", flush=True)
        try:
            payload[name] = measure()
        except Exception:  # recorded: one run on a borrowed GPU should find every problem
            payload[name] = {"error": traceback.format_exc()}
            failed.append(name)
            print(payload[name]["error"], file=sys.stderr, flush=True)
        atomic_write(path, json.dumps(payload, indent=1) + "\n")  # what is measured survives a later crash
        return payload[name]

    job = part("main_job", lambda: main_job(cfg))
    part("latency", lambda: latency(cfg))
    if "error" not in job:
        check = part("agreement", lambda: agreement(cfg, job))
        if "error" not in check and not check["passed"]:
            failed.append("agreement")
        print(f"[device_check] agreement: {json.dumps(check)}")
    payload["failed"] = failed
    atomic_write(path, json.dumps(payload, indent=1) + "\n")
    print(f"[device_check] {'FAILED: ' + ', '.join(failed) if failed else 'passed'} -> {path}")
    if failed:
        raise SystemExit(1)
    return payload


if __name__ == "__main__":
    main(sys.argv[1:])
