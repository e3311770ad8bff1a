"""Results of the detection stage (what ``detection.stage.run`` returns and writes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Defect:
    """One measured defect on the global map. Lengths in metres, map frame = ENU (metres)."""

    id: int
    type: str  # pothole | crack | rut
    severity: str  # low | medium | high
    outline_enu_m: np.ndarray  # (K, 2) closed-or-open outline ring, ENU east/north (m)
    centroid_enu_m: np.ndarray  # (2,) ENU east/north (m)
    max_depth_m: float
    mean_depth_m: float
    area_m2: float
    volume_m3: float  # fill material needed to bring the defect back to the road surface
    length_m: float  # long side of the minimum-area rectangle
    width_m: float  # short side of the minimum-area rectangle
    confidence: float  # 0-1
    frames: list[str] = field(default_factory=list)  # filenames whose footprint saw it


@dataclass
class FrameLabel:
    """Decision for one frame (a row of frames.csv)."""

    filename: str
    defect: int  # 1 defect, 0 not
    p_defect: float  # score in [0, 1]
    source: str  # "3d" | "cnn" | "fused"


@dataclass
class DetectionResult:
    """What the detection stage found; files are in ``run_dir``."""

    defects: list[Defect]
    frames: list[FrameLabel]
    run_dir: Path
    noise_m: float = float("nan")  # σ of the flat-road residual (robust MAD), m
    seed_threshold_m: float = float("nan")  # T_d used on the map, m
    georeferenced: bool = True  # False: no GPS, coordinates are local ENU metres
    files: dict[str, Path] = field(default_factory=dict)

    def table(self) -> str:
        """Short text table of the defects (the CLI prints it)."""
        head = f"{'id':>3} {'type':8} {'sev':6} {'depth mm':>9} {'area m2':>8} {'L x W m':>11} {'conf':>5}"
        lines = [head]
        for d in self.defects:
            lines.append(
                f"{d.id:>3} {d.type:8} {d.severity:6} {1000 * d.max_depth_m:9.1f} "
                f"{d.area_m2:8.3f} {d.length_m:5.2f}x{d.width_m:<5.2f} {d.confidence:5.2f}"
            )
        n_def = sum(f.defect for f in self.frames)
        lines.append(
            f"{len(self.defects)} defect(s); {n_def}/{len(self.frames)} defect frame(s); "
            f"noise σ {1000 * self.noise_m:.2f} mm, T_d {1000 * self.seed_threshold_m:.1f} mm"
            + ("" if self.georeferenced else "; NO GPS: local coordinates only")
        )
        return "\n".join(lines)
