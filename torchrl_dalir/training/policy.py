"""Training a base 3D policy on the expert demos only (its checkpoint: :mod:`torchrl_dalir.checkpoints.policy`).

The policy never sees the mixed-quality data: that is the data asymmetry of DALI-R.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from torchrl_dalir import keys
from torchrl_dalir.checkpoints.policy import load_policy, policy_entries
from torchrl_dalir.config import check_at_least, check_choice, config_dict
from torchrl_dalir.data import TrajectoryDataset
from torchrl_dalir.data.windows import TrajectoryWindows
from torchrl_dalir.envs.make_env import action_bounds
from torchrl_dalir.envs.tasks import ADROIT, METAWORLD, get_task
from torchrl_dalir.modules import ChunkPolicy3D, PolicyConfig, make_policy
from torchrl_dalir.modules.config import BY_TASK, POLICY_KINDS
from torchrl_dalir.objectives import ConsistencyFlowMatchingLoss, DiffusionLoss, FlowMatchingLoss
from torchrl_dalir.reranking.config import RerankingConfig
from torchrl_dalir.training import distributed
from torchrl_dalir.training.logging import make_logger, wandb_mode
from torchrl_dalir.training.loop import OptimConfig, fit
from torchrl_dalir.training.precision import PRECISIONS, autocast_dtype

# What FM regresses on each suite. On Adroit's 24-28-D chunks the velocity target keeps the sampling
# noise after the cpu budget (FM Door 0 %, Pen 22-28 %; the clean chunk: Door 28-84 %, Pen ~70 %,
# docs/measurements.md); MetaWorld keeps the paper's velocity target.
PROTOCOL_FLOW_PREDICTION = {ADROIT: "sample", METAWORLD: "velocity"}


@dataclass
class PolicyTrainingConfig:
    """``examples/train_policy.py``'s configuration; ``policy`` picks the backbone.

    Example:
        >>> from torchrl_dalir.config import parse_config
        >>> # defaults, preset, overrides
        >>> cfg = parse_config(PolicyTrainingConfig, ["preset=smoke", "task=reach"], PRESETS)
        >>> cfg.model.down_dims, cfg.num_steps, cfg.optim.lr, cfg.run_dir().as_posix()
        ([16, 32, 64], 30, 0.001, 'outputs/policies/reach/fm_seed0')
    """

    task: str = "disassemble"
    policy: str = "fm"  # fm | dp
    preset: str = "cpu"
    seed: int = 0
    device: str = "cpu"  # under torchrun, cuda means cuda:<LOCAL_RANK> for each rank
    data: str = "outputs/data"  # demos are read from <data>/<task>/demos
    out: str = "outputs/policies"  # the run writes <out>/<task>/<policy>_seed<seed>/
    model: PolicyConfig = field(default_factory=lambda: PolicyConfig(flow_prediction=BY_TASK))  # FM target: the task's
    optim: OptimConfig = field(default_factory=OptimConfig)
    batch_size: int = 128  # the global batch: under torchrun each of N ranks trains on batch_size / N of it
    epochs: int = 3000  # used when num_steps is 0: epochs over the demo windows
    num_steps: int = 0
    precision: str = "auto"  # auto (bf16 autocast where the hardware runs it natively) | bf16 | fp32
    checkpoint_every: int = 500
    log_every: int = 50
    wandb: str = "off"  # off (CSV only) | offline | online (training/logging.py); true/false: offline/off
    progress: bool = True

    def __post_init__(self):
        spec = get_task(self.task)  # an unknown name fails here, with the list of known ones
        check_choice("policy", self.policy, POLICY_KINDS)
        self.model.kind = self.policy  # the backbone is named once, by ``policy``
        if spec.suite == ADROIT and self.policy == "fm" and self.model.flow_prediction == "velocity":
            warnings.warn(
                f"FM on {spec.name} with the velocity target: on Adroit's 24-28-D chunks it keeps the sampling noise "
                "after the cpu budget (Door: 0 % success, docs/measurements.md); the protocol's Adroit FM predicts "
                "the clean chunk, the default (flow_prediction=task)"
            )  # one place: shown once
        check_choice("precision", self.precision, PRECISIONS)
        self.wandb = wandb_mode(self.wandb)
        for name, minimum in (
            ("batch_size", 1),
            ("epochs", 1),
            ("num_steps", 0),
            ("checkpoint_every", 1),
            ("log_every", 1),
        ):
            check_at_least(name, getattr(self, name), minimum)
        distributed.check_global_batch("batch_size", self.batch_size)

    def resolved(self) -> PolicyTrainingConfig:
        """This configuration with the task's FM target (:data:`PROTOCOL_FLOW_PREDICTION`) in place of
        ``model.flow_prediction="task"``: what a run trains, its checkpoint records and a finished
        run is compared against."""
        if self.model.flow_prediction != BY_TASK:
            return self
        return replace(
            self, model=replace(self.model, flow_prediction=PROTOCOL_FLOW_PREDICTION[get_task(self.task).suite])
        )

    def run_dir(self) -> Path:
        return Path(self.out) / self.task / f"{self.policy}_seed{self.seed}"

    def demos_dir(self) -> Path:
        return Path(self.data) / self.task / "demos"


#: Named overrides of :class:`PolicyTrainingConfig` (``preset=paper|cpu|smoke``); ``paper`` is DP3's setting.
PRESETS: dict[str, dict] = {
    # DP3's configuration: U-Net 512/1024/2048, batch 128, 3000 epochs, AdamW 1e-4.
    "paper": {},
    # One task on a 2-core CPU in about 10 minutes: a 5.3M-parameter U-Net, a larger rate. 1000
    # steps: the reranking protocol's policies (2000 gave weaker MetaWorld policies on the same demos).
    "cpu": {
        "model": {"down_dims": [64, 128, 256]},
        "optim": {"lr": 3e-4, "warmup_steps": 100},
        "batch_size": 64,
        "num_steps": 1000,
    },
    # Seconds, for tests.
    "smoke": {
        "model": {
            "down_dims": [16, 32, 64],
            "point_hidden": [16, 32, 64],
            "ddim_steps": 2,
            "euler_steps": 2,
            "train_timesteps": 20,
        },
        "optim": {"lr": 1e-3, "warmup_steps": 2},
        "batch_size": 8,
        "num_steps": 30,
        "checkpoint_every": 10,
        "log_every": 10,
        "wandb": False,
        "precision": "fp32",  # the same numbers on every machine
    },
}


def _loss_module(policy: ChunkPolicy3D):
    config = policy.config
    if config.kind == "dp":
        return DiffusionLoss(policy)
    if config.flow_objective == "consistency":
        return ConsistencyFlowMatchingLoss(
            policy, config.consistency_delta, config.consistency_segments, config.consistency_alpha
        )
    return FlowMatchingLoss(policy)


def train_policy(cfg: PolicyTrainingConfig) -> Path:
    """Trains (or resumes) a base policy on ``cfg.task``'s demos; returns the checkpoint path.
    Under torchrun, data-parallel over the ranks (only rank 0 writes)."""
    cfg = cfg.resolved()
    device = distributed.setup(cfg.device)
    torch.manual_seed(cfg.seed)
    demos = TrajectoryDataset.load(cfg.demos_dir(), task=cfg.task)
    windows = TrajectoryWindows(demos, cfg.model.obs_steps, cfg.model.horizon, cfg.model.action_steps)
    rows = demos.rows
    acting = ~rows[keys.IS_FINAL]
    policy = make_policy(
        cfg.model,
        action_dim=rows[keys.ACTION].shape[-1],
        state_dim=rows[keys.AGENT_POS].shape[-1],
        task=cfg.task,
        num_points=demos.meta.num_points,
    )
    policy.set_action_bounds(*action_bounds(cfg.task))  # stored in its checkpoint: loading it needs no simulator
    policy.fit_normalizers(rows[keys.POINT_CLOUD], rows[keys.AGENT_POS], rows[keys.ACTION][acting])
    policy.to(device)
    num_steps = cfg.num_steps or cfg.epochs * math.ceil(len(windows) / cfg.batch_size)
    run_dir = cfg.run_dir()
    logger = make_logger(run_dir, f"{cfg.task}_{cfg.policy}_seed{cfg.seed}", wandb=cfg.wandb, config=config_dict(cfg))

    fit(
        _loss_module(policy),
        policy,
        lambda generator: windows.sample(cfg.batch_size, generator),
        num_steps,
        cfg.optim,
        run_dir / "checkpoint.pt",
        lambda ema_policy: policy_entries(ema_policy, config_dict(cfg)),
        seed=cfg.seed,
        checkpoint_every=cfg.checkpoint_every,
        log=logger,
        log_every=cfg.log_every,
        autocast_dtype=autocast_dtype(cfg.precision, device),
        progress=cfg.progress,
    )
    return run_dir / "checkpoint.pt"


def policy_actor(path: str | Path, device: str = "cpu"):
    """A trained policy as a receding-horizon TorchRL actor (picklable as a ``functools.partial``
    of this function, e.g. as a collection :class:`~torchrl_dalir.data.Source`'s policy)."""
    from torchrl_dalir.modules.receding_horizon import receding_horizon

    return receding_horizon(load_policy(path, device))


def exploration_actor(path: str | Path, dropout: float = RerankingConfig.dropout, seed: int = 0, device: str = "cpu"):
    """Like :func:`policy_actor`, but every decision acts on a point-dropout view of the
    observation (:class:`~torchrl_dalir.reranking.candidates.DropoutPolicy`): rollouts of the
    candidates DALI-R chooses among, for the world model's and scorer's data."""
    from torchrl_dalir.modules.receding_horizon import receding_horizon
    from torchrl_dalir.reranking.candidates import DropoutPolicy

    return receding_horizon(DropoutPolicy(load_policy(path, device), dropout, seed))
