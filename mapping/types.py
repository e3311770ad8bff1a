"""Artifacts of the mapping stage shared with detection and the viewer.

``RUN/poses.npz`` holds the fused ``Trajectory`` (see ``save_trajectory``/``load_trajectory``);
``RUN/reference.json`` holds the ENU reference and export CRS. ``PoseReport`` goes to
``RUN/poses_report.json`` and ``MapProducts`` (what the global map wrote) to
``RUN/map_report.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import read_json, write_json_atomic, write_npz_atomic
from roadsurf.core.geometry import (
    EnuReference,
    ExportFrame,
    heading_deg_from_world_rotation,
    mount_angles_deg,
)
from roadsurf.io import runfolder as rf

POSE_SOURCES = ("gps", "visual", "fused")


@dataclass
class Trajectory:
    """Pose of every valid frame in the local ENU map frame (metres)."""

    filenames: list[str]  # (N,) frame filenames
    frame_indices: np.ndarray  # (N,) int Frame.index
    timestamp_s: np.ndarray  # (N,) float
    world_from_cam: np.ndarray  # (N, 4, 4) ENU from camera
    source: list[str]  # (N,) "gps" | "visual" | "fused"
    reference: EnuReference | None  # None: no GPS at all, local frame only (no lat/lon exports)
    # (N,) int: frames in different segments are not tied by vision nor GPS (relative placement of
    # segments is a guess). None = one segment.
    segment: np.ndarray | None = None
    # (3, 3) R_vehicle_from_cam of the camera's mount (mapping.mount); None = nadir
    vehicle_from_cam: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.filenames)

    @property
    def positions_enu_m(self) -> np.ndarray:
        """(N, 3) camera centres."""
        return self.world_from_cam[:, :3, 3]

    @property
    def heading_deg(self) -> np.ndarray:
        """(N,) compass heading of each frame."""
        R_vc = self.vehicle_from_cam
        return np.array(
            [heading_deg_from_world_rotation(T[:3, :3], R_vc) for T in self.world_from_cam]
        )

    @property
    def mount_deg(self) -> tuple[float, float, float] | None:
        """(pitch, roll, yaw) degrees of the mount the poses used; None = nadir."""
        return None if self.vehicle_from_cam is None else mount_angles_deg(self.vehicle_from_cam)

    @property
    def export_frame(self) -> ExportFrame | None:
        return None if self.reference is None else ExportFrame.for_reference(self.reference)


def save_trajectory(run_dir: str | Path, traj: Trajectory) -> None:
    run_dir = Path(run_dir)
    write_npz_atomic(
        run_dir / rf.POSES_NPZ,
        filenames=np.array(traj.filenames, dtype=str),
        frame_indices=np.asarray(traj.frame_indices, dtype=np.int64),
        timestamp_s=np.asarray(traj.timestamp_s, dtype=float),
        world_from_cam=np.asarray(traj.world_from_cam, dtype=float),
        source=np.array(traj.source, dtype=str),
        segment=np.zeros(len(traj), np.int64)
        if traj.segment is None
        else np.asarray(traj.segment, np.int64),
        **(
            {}
            if traj.vehicle_from_cam is None
            else {"vehicle_from_cam": np.asarray(traj.vehicle_from_cam, float)}
        ),
    )
    ref = None
    if traj.reference is not None:
        ef = ExportFrame.for_reference(traj.reference)
        ref = {**traj.reference.to_dict(), "crs": ef.crs}
    write_json_atomic(
        run_dir / rf.REFERENCE_JSON,
        {"reference": ref, "frame": "ENU (x east, y north, z up), metres"},
    )


def load_trajectory(run_dir: str | Path) -> Trajectory:
    run_dir = Path(run_dir)
    meta = read_json(run_dir / rf.REFERENCE_JSON)
    ref = EnuReference.from_dict(meta["reference"]) if meta.get("reference") else None
    with np.load(run_dir / rf.POSES_NPZ, allow_pickle=False) as z:
        return Trajectory(
            filenames=z["filenames"].tolist(),
            frame_indices=z["frame_indices"],
            timestamp_s=z["timestamp_s"],
            world_from_cam=z["world_from_cam"],
            source=z["source"].tolist(),
            reference=ref,
            segment=z["segment"] if "segment" in z.files else None,
            vehicle_from_cam=z["vehicle_from_cam"] if "vehicle_from_cam" in z.files else None,
        )


@dataclass
class PoseReport:
    """What the pose fusion used, rejected and warned about (goes to report.json)."""

    n_frames: int = 0
    n_gps_fixes: int = 0
    n_gps_used: int = 0
    gps_outliers: list[dict[str, Any]] = field(default_factory=list)
    n_pairs_ok: int = 0
    n_pairs_failed: int = 0
    n_pairs_still: int = 0  # of which no_motion: the vehicle stood still (held together)
    n_segments: int = 1
    gps_sigma_scale: float = 1.0
    visual_sigma_scale: float = 1.0
    cost_initial: float = float("nan")
    cost_final: float = float("nan")
    n_iterations: int = 0
    warnings: list[str] = field(default_factory=list)
    # figures of the plausibility checks (mapping.plausibility) and the heights' datum
    checks: dict[str, Any] = field(default_factory=dict)
    vertical_datum: str = ""
    mount: dict[str, Any] = field(default_factory=dict)  # mapping.mount.Mount.to_dict()
    # bundle adjustment's figures (mapping.bundle.refine_poses; issue 30): tracks, windows,
    # reprojection RMS before/after (px), GPS time offset (s) and rejected fixes, time (s);
    # empty when bundle adjustment is off
    bundle: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class MapProducts:
    """What the global-map stage wrote (paths relative to the run folder) and key figures."""

    run_dir: Path
    crs: str | None  # export CRS of cloud.ply and the rasters (None: local ENU frame)
    gsd_m: float
    n_points_raw: int = 0  # points from all ok pairs
    n_points: int = 0  # after voxel fusion
    n_tiles: int = 0
    grid: dict[str, Any] | None = None  # bounding grid of the tile lattice
    files: dict[str, str] = field(default_factory=dict)
    residual_stats_m: dict[str, float] = field(default_factory=dict)
    surface_px: int = 0  # observed pixels in surface.tif
    # ... of which the road model, not measured (seen by one frame only; dense_single_view)
    surface_model_px: int = 0
    mosaic_px: int = 0  # imaged pixels in mosaic.tif
    patch_alignment: dict[str, float] = field(default_factory=dict)
    # share of each frame's road footprint the next frame also sees: median, 10th percentile
    frame_overlap: dict[str, float] = field(default_factory=dict)
    # non-empty tiles: row, col, bounds [x_min, y_min, x_max, y_max] in the grid CRS, and the
    # per-tile files when written, so readers can stay within the corridor (window by window)
    tiles: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)

    def to_report(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["run_dir"] = str(self.run_dir)
        return d

    @classmethod
    def from_report(cls, d: dict[str, Any]) -> MapProducts:
        d = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        d["run_dir"] = Path(d["run_dir"])
        return cls(**d)
