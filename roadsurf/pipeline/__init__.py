"""Pipeline layer: `roadsurf run` and the other end-to-end jobs, calling the stages explicitly."""

from roadsurf.pipeline.run import PipelineConfig, load_pipeline_config, run_drive

__all__ = ["PipelineConfig", "load_pipeline_config", "run_drive"]
