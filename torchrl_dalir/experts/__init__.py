"""Experts that act on privileged simulator state, and the drift noise that degrades them."""

from __future__ import annotations

from tensordict.nn import TensorDictModule

from torchrl_dalir import keys
from torchrl_dalir.envs.tasks import ADROIT, TaskSpec, get_task
from torchrl_dalir.experts.drift_noise import DriftNoise, add_drift_noise
from torchrl_dalir.experts.metaworld import MetaWorldScriptedPolicy


def make_expert(task: str | TaskSpec) -> TensorDictModule:
    """The task's expert: reads ``privileged_state``, writes ``action``.

    MetaWorld tasks use MetaWorld's scripted policies. Adroit experts are not built yet.
    """
    spec = get_task(task)
    if spec.suite == ADROIT:
        raise NotImplementedError(
            f"no expert for the Adroit task {spec.name!r} yet: Adroit experts must be built here "
            "(no checkpoint or dataset can be downloaded); see the Adroit-experts issue"
        )
    return TensorDictModule(MetaWorldScriptedPolicy(spec.env_id), in_keys=[keys.PRIVILEGED_STATE], out_keys=[keys.ACTION])


__all__ = ["DriftNoise", "add_drift_noise", "make_expert"]
