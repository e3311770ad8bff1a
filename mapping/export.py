"""GIS exports of the mapping stage, reusable by other producers (e.g. ``roadsurf sfm-baseline``).

All inputs are in the local ENU frame (metres) with a ``Trajectory`` / ``EnuReference``; the
writers convert to the drive's UTM zone (``ExportFrame``) or to WGS84 lon/lat (GeoJSON).
Without a reference (no GPS) the files stay in the local ENU frame and no lon/lat file is
written.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.geometry import ExportFrame
from roadsurf.io.formats import LOCAL_FRAME_TEXT, feature, write_csv, write_geojson, write_ply
from roadsurf.mapping.datum import RESIDUAL_DATUM
from roadsurf.mapping.types import Trajectory

if TYPE_CHECKING:
    from roadsurf.io.drive import Drive

log = logging.getLogger(__name__)


def export_xyz(enu_m: np.ndarray, export_frame: ExportFrame | None) -> np.ndarray:
    """(N, 3) ENU metres -> (N, 3) export coordinates: UTM easting, northing, height when a
    reference exists, else the ENU coordinates unchanged (local frame)."""
    enu = np.asarray(enu_m, float).reshape(-1, 3)
    if export_frame is None or len(enu) == 0:
        return enu.copy()
    out = np.empty_like(enu)
    for s in range(0, len(enu), 1_000_000):  # bounded pyproj batches
        out[s : s + 1_000_000] = export_frame.utm_from_enu(enu[s : s + 1_000_000])
    return out


def write_cloud_ply(
    path: str | Path,
    xyz_enu_m: np.ndarray,
    rgb: np.ndarray,
    residual_m: np.ndarray,
    export_frame: ExportFrame | None,
    extra: dict[str, np.ndarray] | None = None,
    vertical_datum: str | None = None,
) -> Path:
    """cloud.ply per the output contract: double x,y,z in the export CRS (UTM, or local ENU
    without GPS), uchar red,green,blue, float residual_m (+ ``extra`` per-point properties).
    With ``vertical_datum`` the header names the CRS and the datum of z and of residual_m."""
    xyz = export_xyz(xyz_enu_m, export_frame)
    comments = []
    if vertical_datum:
        crs = export_frame.crs if export_frame is not None else LOCAL_FRAME_TEXT
        comments = [f"crs: {crs}", f"residual_m: {RESIDUAL_DATUM}"]
    return write_ply(
        path,
        xyz,
        rgb,
        {"residual_m": np.asarray(residual_m, np.float32), **(extra or {})},
        vertical_datum=vertical_datum,
        comments=comments,
    )


def write_trajectory_geojson(
    path: str | Path,
    traj: Trajectory,
    drive: Drive | None = None,
    extra: dict[str, Any] | None = None,
    vertical_datum: str | None = None,
) -> Path | None:
    """trajectory.geojson (RFC 7946, WGS84 lon/lat): one LineString of the fused path plus one
    Point per frame with filename, timestamp_s, heading_deg, source (and frame_index, segment,
    easting_m, northing_m, height_m in ``vertical_datum``, named in the collection's
    properties). Returns None (and writes nothing, removing an earlier run's file) without a
    reference (no GPS)."""
    ef = traj.export_frame
    if ef is None:
        log.warning("trajectory.geojson not written: no GPS reference (local frame only)")
        # an earlier run of the folder with GPS left one: its lon/lat would contradict this run
        Path(path).unlink(missing_ok=True)
        return None
    pos = traj.positions_enu_m
    lonlat = ef.lonlat_from_enu(pos)
    utm = ef.utm_from_enu(pos)
    heading = traj.heading_deg
    seg = traj.segment if traj.segment is not None else np.zeros(len(traj), int)
    feats = []
    if len(traj) >= 2:
        feats.append(
            feature(
                {"type": "LineString", "coordinates": lonlat.tolist()},
                {"kind": "trajectory", "n_frames": len(traj), "crs_utm": ef.crs},
            )
        )
    for i in range(len(traj)):
        feats.append(
            feature(
                {"type": "Point", "coordinates": lonlat[i].tolist()},
                {
                    "filename": traj.filenames[i],
                    "timestamp_s": float(traj.timestamp_s[i]),
                    "heading_deg": float(heading[i]),
                    "source": traj.source[i],
                    "frame_index": int(traj.frame_indices[i]),
                    "segment": int(seg[i]),
                    "easting_m": float(utm[i, 0]),
                    "northing_m": float(utm[i, 1]),
                    "height_m": float(utm[i, 2]),
                },
            )
        )
    props = {"crs_utm": ef.crs, "reference": traj.reference.to_dict(), **(extra or {})}
    return write_geojson(path, feats, props, vertical_datum=vertical_datum)


def write_trajectory_csv(path: str | Path, traj: Trajectory) -> Path:
    """trajectory.csv: per frame ENU position (and UTM/lon/lat when a reference exists)."""
    ef = traj.export_frame
    pos = traj.positions_enu_m
    heading = traj.heading_deg
    header = ["filename", "timestamp_s", "east_m", "north_m", "up_m", "heading_deg", "source"]
    utm = lonlat = None
    if ef is not None:
        # the zone rides on every row: a drive on a zone border is in one of two
        header += ["easting_m", "northing_m", "lon_deg", "lat_deg", "crs"]
        utm, lonlat = ef.utm_from_enu(pos), ef.lonlat_from_enu(pos)
    rows = []
    for i in range(len(traj)):
        r: list[Any] = [traj.filenames[i], float(traj.timestamp_s[i]), *pos[i].tolist()]
        r += [float(heading[i]), traj.source[i]]
        if utm is not None and lonlat is not None:
            r += [utm[i, 0], utm[i, 1], lonlat[i, 0], lonlat[i, 1], ef.crs]
        rows.append(r)
    return write_csv(path, header, rows)
