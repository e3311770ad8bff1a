"""Results of the detection stage (what ``detection.stage.run`` returns and writes)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# The serialised defect record: defects.geojson properties and defects.csv columns, in order.
DEFECT_COLUMNS = (
    "id",
    "type",
    "severity",
    "max_depth_m",
    "mean_depth_m",
    "area_m2",
    "volume_m3",
    "length_m",
    "width_m",
    "confidence",
    "frames",
    "centroid_lon",
    "centroid_lat",
    "centroid_e_m",
    "centroid_n_m",
    "measured_on",
    "profiles",
)
_MEASURES = ("max_depth_m", "mean_depth_m", "area_m2", "volume_m3", "length_m", "width_m")


def _num(props: dict[str, Any], key: str) -> float:
    try:
        v = props.get(key)
        return float(v) if v is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


def _int(props: dict[str, Any], key: str) -> int:
    try:
        return int(float(props.get(key) or 0))
    except (TypeError, ValueError):
        return 0


@dataclass
class Defect:
    """One measured defect on the global map. Lengths in metres; coordinates in the map's grid
    frame (``DetectionResult.crs``: the UTM zone with GPS, local ENU without)."""

    id: int
    type: str  # pothole | crack | rut
    severity: str  # low | medium | high
    outline_xy_m: np.ndarray  # (K, 2) outline ring (not closed), easting/northing (m)
    centroid_xy_m: np.ndarray  # (2,) easting/northing (m)
    max_depth_m: float
    mean_depth_m: float
    area_m2: float
    volume_m3: float  # fill material needed to bring the defect back to the road surface
    length_m: float  # long side of the minimum-area rectangle
    width_m: float  # short side of the minimum-area rectangle
    confidence: float  # 0-1
    frames: list[str] = field(default_factory=list)  # filenames whose footprint saw it
    # where a crack's width and depth come from (``crackraster``): "raster" (profiles across it
    # on surface.tif, where the raster resolves it), "points" (the pairs' points and dense
    # tracks) or "image" (kept on the images where the 3D tests are blind, ``crackimage``: no
    # depth, max_depth_m NaN); "" for other types
    measured_on: str = ""
    profiles: int = 0  # raster profiles across the crack that were read (count; 0: none)

    def to_properties(self, lonlat: np.ndarray | None, exact: bool = False) -> dict[str, Any]:
        """The record as written (DEFECT_COLUMNS order): rounded for the GIS files, ``exact``
        for detection.json. ``lonlat`` (2,) is the centroid in WGS84, None without GPS."""

        def r(v: float, n: int) -> float:
            return float(v) if exact else round(float(v), n)

        return {
            "id": self.id,
            "type": self.type,
            "severity": self.severity,
            "max_depth_m": r(self.max_depth_m, 5),
            "mean_depth_m": r(self.mean_depth_m, 5),
            "area_m2": r(self.area_m2, 6),
            "volume_m3": r(self.volume_m3, 8),
            "length_m": r(self.length_m, 4),
            "width_m": r(self.width_m, 4),
            "confidence": r(self.confidence, 3),
            "frames": list(self.frames),
            "centroid_lon": None if lonlat is None else float(lonlat[0]),
            "centroid_lat": None if lonlat is None else float(lonlat[1]),
            "centroid_e_m": r(self.centroid_xy_m[0], 4),
            "centroid_n_m": r(self.centroid_xy_m[1], 4),
            "measured_on": self.measured_on,
            "profiles": int(self.profiles),
        }

    @staticmethod
    def fields_from_properties(props: dict[str, Any], default_id: int = 0) -> dict[str, Any]:
        """The record's fields read back from written properties, tolerantly (missing or
        non-numeric measures become NaN): every field but the outline and centroid."""
        try:
            ident = int(props.get("id", default_id))
        except (TypeError, ValueError):
            ident = default_id
        return {
            "id": ident,
            "type": str(props.get("type", "defect")),
            "severity": str(props.get("severity", "unknown")),
            **{k: _num(props, k) for k in _MEASURES},
            "confidence": _num(props, "confidence"),
            "frames": [str(x) for x in (props.get("frames") or [])],
            # absent in files written before these fields existed
            "measured_on": str(props.get("measured_on") or ""),
            "profiles": _int(props, "profiles"),
        }


@dataclass
class FrameLabel:
    """Decision for one frame (a row of frames.csv)."""

    filename: str
    # 1 defect, 0 not; None: not analysed (no ok pair saw the frame, it has no place on the map
    # and no CNN screened it), an empty cell in frames.csv, never "no defect"
    defect: int | None
    p_defect: float | None  # score in [0, 1]; None when not analysed
    source: str  # "3d" | "cnn" | "fused" | "none" (NOT_ANALYSED)


NOT_ANALYSED = "none"  # FrameLabel.source of a frame nothing measured


@dataclass
class DetectionResult:
    """What the detection stage found; files are in ``run_dir``."""

    defects: list[Defect]
    frames: list[FrameLabel]
    run_dir: Path
    noise_m: float = float("nan")  # σ of the flat-road residual (robust MAD), m
    seed_threshold_m: float = float("nan")  # T_d used on the map, m
    georeferenced: bool = True  # False: no GPS, coordinates are local ENU metres
    crs: str = ""  # grid frame of the outlines: "EPSG:326xx" or "local ENU"
    surface_source: str = ""  # surface.tif | map_points.npz | pairs | none
    files: dict[str, Path] = field(default_factory=dict)
    # what a user must know about a measurement (report.json "warnings"; kept in detection.json)
    warnings: list[str] = field(default_factory=list)

    def to_report(self) -> dict[str, Any]:
        """Summary for report.json."""
        by_type: dict[str, int] = {}
        for d in self.defects:
            by_type[d.type] = by_type.get(d.type, 0) + 1
        return {
            "defects": len(self.defects),
            "by_type": by_type,
            "defect_frames": int(sum(1 for f in self.frames if f.defect)),
            "frames_not_analysed": int(sum(1 for f in self.frames if f.defect is None)),
            "frames": len(self.frames),
            "noise_m": self.noise_m,
            "seed_threshold_m": self.seed_threshold_m,
            "georeferenced": self.georeferenced,
            "crs": self.crs,
            "surface_source": self.surface_source,
            "warnings": list(self.warnings),
            "files": {k: str(v) for k, v in self.files.items()},
            "table": self.table(),  # printable summary (the CLI shows it after `roadsurf run`)
        }

    def table(self) -> str:
        """Short text table of the defects (the CLI prints it)."""
        head = f"{'id':>3} {'type':8} {'sev':6} {'depth mm':>9} {'area m2':>8} {'L x W mm':>11} {'conf':>5}"
        lines = [head]
        for d in self.defects:
            lines.append(
                f"{d.id:>3} {d.type:8} {d.severity:6} {_mm(d.max_depth_m):>9} "
                f"{d.area_m2:8.3f} {1000 * d.length_m:5.0f}x{1000 * d.width_m:<5.0f} {d.confidence:5.2f}"
            )
        n_def = sum(1 for f in self.frames if f.defect)
        lines.append(
            f"{len(self.defects)} defect(s); {n_def}/{len(self.frames)} defect frame(s); "
            f"noise σ {1000 * self.noise_m:.2f} mm, T_d {1000 * self.seed_threshold_m:.1f} mm"
            + ("" if self.georeferenced else "; NO GPS: local coordinates only")
        )
        return "\n".join(lines)


def _mm(v_m: float) -> str:
    """A depth in mm for the text table; "-" where it was not measured (NaN)."""
    return f"{1000 * v_m:.1f}" if math.isfinite(v_m) else "-"
