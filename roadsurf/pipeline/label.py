"""The CNN labelling job (`roadsurf label`): the physics pipeline labels the frames of drives.

For every drive the physics pipeline runs (or a finished run folder is reused); the classifier
package then labels that run's frames (``detection.classifier.dataset.label_run``, the rule in
``detection.classifier.selflabel``) and writes the dataset (``write_dataset``: augmentation,
labels.csv, balance.json, dataset.json). It sits at the pipeline layer because it runs the
whole pipeline; the detection stage itself never imports the pipeline.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from roadsurf.core.atomic import output_error
from roadsurf.core.errors import RoadsurfError
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.dataset import drive_key, label_run, write_dataset
from roadsurf.io.runfolder import RunFolder
from roadsurf.pipeline.run import load_pipeline_config, run_drive

log = logging.getLogger(__name__)


def classifier_config(config_path: str | Path | None = None, **overrides: Any) -> ClassifierConfig:
    """ClassifierConfig from a pipeline YAML (its ``classifier:`` section) plus overrides
    (None values are left out)."""
    cfg = (
        ClassifierConfig() if config_path is None else load_pipeline_config(config_path).classifier
    )
    kw = {k: v for k, v in overrides.items() if v is not None}
    return dataclasses.replace(cfg, **kw) if kw else cfg


def ensure_run(drive_dir: Path, run_dir: Path) -> Path:
    """Reuse a finished run folder, else run (or resume) the physics pipeline into it."""
    run = RunFolder(run_dir)
    if run.report.is_file() and run.pairs_dir.is_dir():
        log.info("reusing finished run %s for %s", run_dir, drive_dir)
        return run_dir
    log.info("running the physics pipeline on %s into %s", drive_dir, run_dir)
    run_drive(drive_dir, run_dir)
    return run_dir


def label_drives(
    drives: Sequence[str | Path],
    out: str | Path,
    cfg: ClassifierConfig | None = None,
    *,
    runs: Sequence[str | Path] | None = None,
    runs_dir: str | Path | None = None,
) -> dict[str, Any]:
    """Label every frame of ``drives`` with the physics pipeline and write the dataset ``out``.

    ``runs`` gives a finished run folder per drive (same order); otherwise each drive's run
    lives in ``runs_dir/<key>`` (default ``out/runs``) and is computed or resumed there.
    Returns the balance summary (also ``out/balance.json``).
    """
    cfg = cfg or ClassifierConfig()
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # a file in the way, a read-only folder
        raise output_error(e, out) from e
    drive_dirs = [Path(d) for d in drives]
    if runs is not None and len(runs) != len(drive_dirs):
        raise RoadsurfError(
            f"--run given {len(runs)} times for {len(drive_dirs)} drives; give one run folder "
            "per drive (in the same order) or none"
        )
    rdir = Path(runs_dir) if runs_dir is not None else out / "runs"
    rows: list[dict[str, Any]] = []
    dropped: dict[str, int] = {}
    provenance = []
    t0 = time.perf_counter()
    for i, ddir in enumerate(drive_dirs):
        key = drive_key(i, ddir)
        run_dir = Path(runs[i]) if runs is not None else ensure_run(ddir, rdir / key)
        if runs is not None and not RunFolder(run_dir).pairs_dir.is_dir():
            raise RoadsurfError(
                f"{run_dir}: not a finished run folder (no pairs/); run `roadsurf run {ddir} "
                f"--out {run_dir}` first or leave out --run"
            )
        one = label_run(ddir, run_dir, key, out, cfg)
        rows += one.rows
        for rule, n in one.dropped.items():  # first-seen order across drives, as one count
            dropped[rule] = dropped.get(rule, 0) + n
        provenance.append(one.provenance)
    return write_dataset(out, rows, dropped, provenance, cfg, t0)


def run_label(
    drives: list[Path],
    out: Path,
    *,
    runs: list[Path] | None = None,
    runs_dir: Path | None = None,
    config_path: Path | None = None,
    augment: bool | None = None,
) -> dict[str, Any]:
    """`roadsurf label`: ``label_drives`` with the config file's ``classifier:`` section."""
    cfg = classifier_config(config_path, augment=augment)
    return label_drives(drives, out, cfg, runs=runs or None, runs_dir=runs_dir)
