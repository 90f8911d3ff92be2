"""The main job: its configuration (:class:`PipelineConfig`, presets) and its stages (:func:`run_pipeline`)."""

from torchrl_dalir.pipeline.config import DERIVED_FROM, PRESETS, STAGES, PipelineConfig
from torchrl_dalir.pipeline.run import run_pipeline

__all__ = ["DERIVED_FROM", "PRESETS", "STAGES", "PipelineConfig", "run_pipeline"]
