"""What the viewer and the report know about a run: ``RunData`` (everything read from a run
folder, in the local ENU frame), ``DefectView`` (one defect), ``Raster`` (a decimated GeoTIFF),
and how defect severities rank and colour."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.geometry import EnuReference, ExportFrame
from roadsurf.detection.types import Defect
from roadsurf.io.formats import GridSpec

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

    from roadsurf.io.drive import Drive
    from roadsurf.mapping.types import Trajectory
    from roadsurf.reconstruction.types import PairResult

SEVERITY_RANK = {"high": 3, "medium": 2, "low": 1}
SEVERITY_RGB = {
    "high": (220, 30, 30),
    "medium": (255, 140, 0),
    "low": (240, 210, 40),
}
UNKNOWN_RGB = (150, 150, 150)


def depth_text(depth_m: float | None, decimals: int = 1) -> str:
    """A defect's depth for people: "12.3 mm", or "depth not measured" (a crack kept on the
    images alone, whose depth is NaN / null)."""
    if depth_m is None or not math.isfinite(depth_m):
        return "depth not measured"
    return f"{1000 * depth_m:.{decimals}f} mm"


def severity_rank(sev: object) -> int:
    """Sort key of a severity label (high > medium > low > anything else)."""
    s = str(sev).strip().lower()
    s = {"h": "high", "m": "medium", "l": "low"}.get(s, s)
    if s in SEVERITY_RANK:
        return SEVERITY_RANK[s]
    try:  # numeric severities (1..3) sort by value
        return int(float(s))
    except ValueError:
        return 0


def severity_rgb(sev: object) -> tuple[int, int, int]:
    s = str(sev).strip().lower()
    s = {"h": "high", "m": "medium", "l": "low"}.get(s, s)
    return SEVERITY_RGB.get(s, UNKNOWN_RGB)


@dataclass(kw_only=True)
class DefectView(Defect):
    """The detection stage's defect record as the viewer holds it: ``outline_xy_m`` and
    ``centroid_xy_m`` in the local ENU frame (m) instead of the map's grid frame, plus the
    closed ring in ENU and, when georeferenced, in lon/lat."""

    ring_enu_m: np.ndarray  # (K, 2) closed outline, east/north (m)
    ring_lonlat: np.ndarray | None = None  # (K, 2) lon/lat degrees, None without GPS

    @property
    def centroid_enu_m(self) -> np.ndarray:
        return self.centroid_xy_m

    @property
    def label(self) -> str:
        return (
            f"#{self.id} {self.type} {depth_text(self.max_depth_m, 0)} "
            f"{self.area_m2:.3f} m² {self.severity}"
        )


@dataclass
class Raster:
    """A (possibly decimated) GeoTIFF: data is (H, W) float32 with NaN nodata or (H, W, 3) uint8."""

    data: np.ndarray
    grid: GridSpec  # grid of ``data`` (gsd already scaled by the decimation)
    path: Path


@dataclass
class RunData:
    """Everything the viewer found in a run folder. ``None`` means the file is absent."""

    run_dir: Path
    report: dict[str, Any]
    reference: EnuReference | None
    crs: str | None
    trajectory: Trajectory | None
    cloud_enu_m: np.ndarray | None  # (N, 3) float64
    cloud_rgb: np.ndarray | None  # (N, 3) uint8
    cloud_residual_m: np.ndarray | None  # (N,) float
    defects: list[DefectView]
    frame_labels: dict[str, dict[str, str]]  # filename -> row of frames.csv
    pairs: list[PairResult]  # sorted by index_a
    mosaic: Raster | None
    surface: Raster | None
    masks: dict[str, Path]  # frame filename (stem) -> refined 2D defect mask image
    drive: Drive | None
    missing: list[str] = field(default_factory=list)

    @functools.cached_property
    def cloud_tree_xy(self) -> cKDTree:
        """KD-tree (scipy cKDTree) of the cloud's east/north coordinates."""
        from scipy.spatial import cKDTree

        xy = self.cloud_enu_m[:, :2] if self.cloud_enu_m is not None else np.zeros((0, 2))
        return cKDTree(xy)

    @property
    def export_frame(self) -> ExportFrame | None:
        return None if self.reference is None else ExportFrame.for_reference(self.reference)

    def lonlat_from_enu(self, enu_m: np.ndarray) -> np.ndarray | None:
        """(N, 2|3) ENU -> (N, 2) lon/lat, or None without a reference."""
        ef = self.export_frame
        return None if ef is None else ef.lonlat_from_enu(enu_m)


def sort_defects(defects: list[DefectView]) -> list[DefectView]:
    """Most severe first, then deepest first."""
    return sorted(
        defects,
        key=lambda d: (
            -severity_rank(d.severity),
            -(d.max_depth_m if math.isfinite(d.max_depth_m) else -1.0),
        ),
    )
