"""Train DALI-R's latent encoder, task-completion scorer and latent world model on a task's mixed data.

    python examples/train_world_model.py task=disassemble preset=cpu \\
        policy_checkpoint=outputs/policies/disassemble/fm_seed0/checkpoint.pt
    torchrun --nproc_per_node=2 examples/train_world_model.py task=disassemble preset=cpu policy_checkpoint=...

(under torchrun the trainings are data-parallel, the batch sizes global, and rank 0 alone writes and prints).

Reads ``<data>/<task>/mixed``; writes ``<out>/<task>/seed<seed><variant>/world_model.pt`` (``seed0_frozen``
under the ``cpu`` preset, which keeps the policy's encoder frozen) with the
held-out metrics (scorer Brier score and calibration error, world-model MSE next to the
"no change" predictor), which it prints.
"""

from __future__ import annotations

import json
import sys

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.checkpoints import load_world_model
from torchrl_dalir.config import parse_config
from torchrl_dalir.training import WORLD_MODEL_PRESETS, WorldModelTrainingConfig, distributed, train_world_model


def main(argv: list[str]) -> None:
    cfg = parse_config(WorldModelTrainingConfig, argv, WORLD_MODEL_PRESETS)
    path = train_world_model(cfg)
    if not distributed.is_main():
        return
    print(path)
    print(json.dumps(load_world_model(path).metrics, indent=1))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
