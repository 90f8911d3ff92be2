"""DALI-R end to end on one task: demos -> base policy -> mixed data -> exploration -> world model -> calibration
-> evaluation.

    python examples/train_dp3_wm.py                                  # disassemble, cpu preset
    python examples/train_dp3_wm.py task=shelf-place policy=dp seed=1
    python examples/train_dp3_wm.py preset=smoke out=/tmp/dalir      # about a minute, for tests

The configuration is :class:`torchrl_dalir.pipeline.PipelineConfig` (``key=value`` overrides, a
``preset``) and the stages are :func:`torchrl_dalir.pipeline.run_pipeline`: each is skipped once
its artifact is complete, an interrupted one resumes, ``redo=[world_model]`` runs that stage and
the later ones again. The results (a markdown table, JSON and the diagnostic plots) go to
``<out>/results/<task>/<policy>_seed<seed><variant>/``.
"""

from __future__ import annotations

import sys

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.config import parse_config
from torchrl_dalir.pipeline import PRESETS, PipelineConfig, run_pipeline


def main(argv: list[str]) -> None:
    run_pipeline(parse_config(PipelineConfig, argv, PRESETS))


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
