"""Artifacts of the mapping stage shared with detection and the viewer.

``RUN/poses.npz`` holds the fused ``Trajectory`` (see ``save_trajectory``/``load_trajectory``);
``RUN/reference.json`` holds the ENU reference and export CRS.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roadsurf.core.atomic import read_json, write_json_atomic, write_npz_atomic
from roadsurf.core.geometry import EnuReference, ExportFrame, heading_deg_from_world_rotation

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

    def __len__(self) -> int:
        return len(self.filenames)

    @property
    def positions_enu_m(self) -> np.ndarray:
        """(N, 3) camera centres."""
        return self.world_from_cam[:, :3, 3]

    @property
    def heading_deg(self) -> np.ndarray:
        """(N,) compass heading of each frame."""
        return np.array([heading_deg_from_world_rotation(T[:3, :3]) for T in self.world_from_cam])

    @property
    def export_frame(self) -> ExportFrame | None:
        return None if self.reference is None else ExportFrame.for_reference(self.reference)


def save_trajectory(run_dir: str | Path, traj: Trajectory) -> None:
    run_dir = Path(run_dir)
    write_npz_atomic(
        run_dir / "poses.npz",
        filenames=np.array(traj.filenames, dtype=str),
        frame_indices=np.asarray(traj.frame_indices, dtype=np.int64),
        timestamp_s=np.asarray(traj.timestamp_s, dtype=float),
        world_from_cam=np.asarray(traj.world_from_cam, dtype=float),
        source=np.array(traj.source, dtype=str),
        segment=np.zeros(len(traj), np.int64)
        if traj.segment is None
        else np.asarray(traj.segment, np.int64),
    )
    ref = None
    if traj.reference is not None:
        ef = ExportFrame.for_reference(traj.reference)
        ref = {**traj.reference.to_dict(), "crs": ef.crs}
    write_json_atomic(
        run_dir / "reference.json",
        {"reference": ref, "frame": "ENU (x east, y north, z up), metres"},
    )


def load_trajectory(run_dir: str | Path) -> Trajectory:
    run_dir = Path(run_dir)
    meta = read_json(run_dir / "reference.json")
    ref = EnuReference.from_dict(meta["reference"]) if meta.get("reference") else None
    with np.load(run_dir / "poses.npz", allow_pickle=False) as z:
        return Trajectory(
            filenames=z["filenames"].tolist(),
            frame_indices=z["frame_indices"],
            timestamp_s=z["timestamp_s"],
            world_from_cam=z["world_from_cam"],
            source=z["source"].tolist(),
            reference=ref,
            segment=z["segment"] if "segment" in z.files else None,
        )
