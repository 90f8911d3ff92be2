"""Configuration of the base 3D policies (DP3 diffusion and 3D flow matching)."""

from __future__ import annotations

from dataclasses import dataclass, field

from torchrl_dalir.config import check_choice

POLICY_KINDS = ("dp", "fm")  # DDIM diffusion (DP3), linear-path flow matching
FLOW_PREDICTIONS = ("velocity", "sample")  # what the flow-matching network outputs
BY_TASK = "task"  # a training configuration's flow_prediction: the task's protocol target, resolved before building


def executed_slice(obs_steps: int, action_steps: int) -> slice:
    """The chunk entries executed at a decision: a chunk starts at the oldest observation step,
    so the current step is entry ``obs_steps - 1``."""
    return slice(obs_steps - 1, obs_steps - 1 + action_steps)


@dataclass
class PolicyConfig:
    """Architecture and sampler of a base policy. Defaults are DP3's (the ``paper`` preset).

    Args:
        kind: ``"dp"`` (DDIM diffusion, clean-sample prediction) or ``"fm"`` (linear-path flow
            matching, Euler integration).
        horizon: predicted chunk length ``H``; the chunk starts at the oldest observation step.
        obs_steps: observation-history length ``To``.
        action_steps: actions executed per decision, starting at chunk index ``To - 1``.
        point_hidden, point_out: per-point MLP widths and pooled feature size.
        state_out: robot-state feature size.
        down_dims, kernel_size, groups, step_embed_dim: the conditional U-Net.
        train_timesteps: diffusion steps in training (also the time scale of the FM embedding).
        ddim_steps: DDIM denoising steps at inference (``dp``; DP3: 10).
        euler_steps: Euler steps, i.e. network evaluations, at inference (``fm``).
        beta_schedule, clip_sample: DDIM noise schedule and clipping of the predicted sample.
        flow_objective: ``"flow_matching"`` (plain linear-path regression) or ``"consistency"``
            (FlowPolicy's consistency flow matching, meant for one Euler step).
        flow_prediction: what the FM network outputs: ``"velocity"`` (the paper's flow matching) or
            ``"sample"`` (the clean chunk, as DP3's diffusion does; the velocity is derived from it).
            On Adroit Door's 28-D chunks the velocity target left most of the noise in the samples
            after the ``cpu`` budget, the clean-chunk target did not (``docs/results`` and README).
            With one Euler step a sample-predicting network returns its estimate of the chunk, so
            its candidates differ by their inputs (point dropout) more than by their noise.
            ``"task"`` (training configurations' default) stands for the task's protocol target,
            ``"sample"`` on Adroit and ``"velocity"`` on MetaWorld; it is resolved before a
            policy is built (:meth:`~torchrl_dalir.training.PolicyTrainingConfig.resolved`).
        consistency_delta, consistency_segments, consistency_alpha: its time gap, number of
            path segments and velocity-term weight.

    Example:
        >>> config = PolicyConfig(kind="dp", down_dims=[64, 128, 256])
        >>> config.horizon, config.obs_steps, config.executed  # 16-action chunks, actions 1 .. 8 executed
        (16, 2, slice(1, 9, None))
        >>> PolicyConfig(horizon=8)
        Traceback (most recent call last):
        ValueError: obs_steps - 1 + action_steps must not exceed the horizon
    """

    kind: str = "fm"
    horizon: int = 16
    obs_steps: int = 2
    action_steps: int = 8
    point_hidden: list[int] = field(default_factory=lambda: [64, 128, 256])
    point_out: int = 64
    state_out: int = 64
    down_dims: list[int] = field(default_factory=lambda: [512, 1024, 2048])
    kernel_size: int = 5
    groups: int = 8
    step_embed_dim: int = 128
    train_timesteps: int = 100
    ddim_steps: int = 10
    euler_steps: int = 1
    beta_schedule: str = "squaredcos_cap_v2"
    clip_sample: bool = True
    flow_objective: str = "flow_matching"
    flow_prediction: str = "velocity"
    consistency_delta: float = 0.01
    consistency_segments: int = 2
    consistency_alpha: float = 1e-5

    def __post_init__(self):
        check_choice("policy kind", self.kind, POLICY_KINDS)
        check_choice("flow_objective", self.flow_objective, ("flow_matching", "consistency"))
        check_choice("flow_prediction", self.flow_prediction, (*FLOW_PREDICTIONS, BY_TASK))
        if self.obs_steps - 1 + self.action_steps > self.horizon:
            raise ValueError("obs_steps - 1 + action_steps must not exceed the horizon")

    @property
    def executed(self) -> slice:
        """The chunk entries executed at a decision (see :func:`executed_slice`)."""
        return executed_slice(self.obs_steps, self.action_steps)
