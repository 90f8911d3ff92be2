"""Experts that act on privileged simulator state, and the drift noise that degrades them."""

from __future__ import annotations

from tensordict.nn import TensorDictModule

from torchrl_dalir import keys
from torchrl_dalir.envs.tasks import ADROIT, TaskSpec, get_task
from torchrl_dalir.experts.adroit_door import DoorScriptedPolicy
from torchrl_dalir.experts.adroit_pen import PenExpertPolicy
from torchrl_dalir.experts.drift_noise import DriftNoise, add_drift_noise
from torchrl_dalir.experts.metaworld import MetaWorldScriptedPolicy


def make_expert(task: str | TaskSpec) -> TensorDictModule:
    """The task's expert: reads ``privileged_state``, writes ``action``.

    MetaWorld tasks use MetaWorld's scripted policies; Door a scripted controller
    (:class:`DoorScriptedPolicy`); Pen a PPO policy trained here, shipped with the package
    (:class:`PenExpertPolicy`, rebuilt by ``examples/maintainer/train_pen_expert.py``).
    """
    spec = get_task(task)
    if spec.suite == ADROIT:
        experts = {"door": DoorScriptedPolicy, "pen": PenExpertPolicy.load}
        if spec.name not in experts:
            raise NotImplementedError(
                f"no expert for the Adroit task {spec.name!r}; Adroit experts exist for {sorted(experts)}"
            )
        return TensorDictModule(experts[spec.name](), in_keys=[keys.PRIVILEGED_STATE], out_keys=[keys.ACTION])
    return TensorDictModule(
        MetaWorldScriptedPolicy(spec.env_id), in_keys=[keys.PRIVILEGED_STATE], out_keys=[keys.ACTION]
    )


__all__ = ["DoorScriptedPolicy", "DriftNoise", "PenExpertPolicy", "add_drift_noise", "make_expert"]
