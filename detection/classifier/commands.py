"""Entry points of the `roadsurf label`, `train` and `bench classifier` commands.

Each takes the command's plain arguments, builds the configuration (a pipeline YAML's
``classifier:`` section plus command-line overrides) and calls one stage function.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from roadsurf.detection.classifier.config import ClassifierConfig


def make_config(config_path: str | Path | None = None, **overrides: Any) -> ClassifierConfig:
    """ClassifierConfig from a pipeline YAML (its ``classifier:`` section) plus overrides."""
    if config_path is None:
        cfg = ClassifierConfig()
    else:
        from roadsurf.pipeline import load_pipeline_config

        cfg = load_pipeline_config(config_path).classifier
    kw = {k: v for k, v in overrides.items() if v is not None}
    return dataclasses.replace(cfg, **kw) if kw else cfg


def label(
    drives: list[Path],
    out: Path,
    *,
    runs: list[Path] | None = None,
    runs_dir: Path | None = None,
    config_path: Path | None = None,
    augment: bool | None = None,
) -> dict[str, Any]:
    from roadsurf.detection.classifier.dataset import label_drives

    cfg = make_config(config_path, augment=augment)
    return label_drives(drives, out, cfg, runs=runs or None, runs_dir=runs_dir)


def train(
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
    from roadsurf.detection.classifier.train import train as _train

    cfg = make_config(
        config_path,
        epochs=epochs,
        learning_rate=learning_rate,
        input_size_px=input_size_px,
        seed=seed,
    )
    return _train(dataset, out, cfg, resume=not overwrite)


def bench(
    work: Path,
    *,
    quick: bool = False,
    config_path: Path | None = None,
    epochs: int | None = None,
    learning_rate: float | None = None,
) -> dict[str, Any]:
    from roadsurf.detection.classifier.bench import bench_classifier, require_simulator

    require_simulator()
    cfg = make_config(config_path, epochs=epochs, learning_rate=learning_rate)
    return bench_classifier(work, cfg, quick=quick, config_path=config_path)
