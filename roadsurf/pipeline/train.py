"""The CNN training job (`roadsurf train`): a pipeline config file's ``classifier:`` section
plus command-line overrides, then ``detection.classifier.train.train``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from roadsurf.pipeline.label import classifier_config


def run_train(
    dataset: Path,
    out: Path,
    *,
    config_path: Path | None = None,
    epochs: int | None = None,
    learning_rate: float | None = None,
    input_size_px: int | None = None,
    seed: int | None = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Train on ``dataset`` into the model folder ``out`` (resumes unless ``overwrite``);
    returns the model metadata written."""
    # torch is imported only when training: `roadsurf label` and the CLI start stay light
    from roadsurf.detection.classifier.train import train

    cfg = classifier_config(
        config_path,
        epochs=epochs,
        learning_rate=learning_rate,
        input_size_px=input_size_px,
        seed=seed,
    )
    return train(dataset, out, cfg, resume=not overwrite)
