"""Detection stage entry point: per-pair 3D segmentation, global-map defects, GIS outputs.

``run(cfg, drive, pairs, traj, run_dir, *, frame_probs=None) -> DetectionResult`` writes
RUN/defects.geojson, RUN/defects.csv and RUN/frames.csv (see docs/detection.md).
"""

from __future__ import annotations

import logging
from pathlib import Path

from detection.config import DetectionConfig
from detection.types import DetectionResult, FrameLabel
from mapping.types import Trajectory
from reconstruction.types import PairResult
from roadsurf.drive import Drive
from roadsurf.formats import write_csv, write_geojson

log = logging.getLogger(__name__)


def run(
    cfg: DetectionConfig,
    drive: Drive,
    pairs: list[PairResult],
    traj: Trajectory,
    run_dir: Path,
    *,
    frame_probs: dict[str, float] | None = None,
) -> DetectionResult:
    """Detect and measure defects; write the three output files into ``run_dir``.

    Preliminary version: frame labels only (no measured defects yet).
    """
    run_dir = Path(run_dir)
    frames = [FrameLabel(f.filename, 0, 0.0, "3d") for f in drive.frames]
    geo = traj.reference is not None
    write_geojson(run_dir / "defects.geojson", [], {"georeferenced": geo})
    write_csv(run_dir / "defects.csv", ["id"], [])
    write_csv(
        run_dir / "frames.csv",
        ["filename", "defect", "p_defect", "source"],
        [(f.filename, f.defect, f.p_defect, f.source) for f in frames],
    )
    return DetectionResult([], frames, run_dir, georeferenced=geo)
