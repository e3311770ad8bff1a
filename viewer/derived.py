"""Geometry derived from a loaded run: GPS fixes and defect outlines in ENU, the road height
near a point, projection into a frame and onto a raster grid. Metres (ENU: x east, y north,
z up) and pixels (u right, v down)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.geometry import enu_from_lla, invert_pose, transform_points
from roadsurf.io.formats import GridSpec
from roadsurf.viewer.rundata import DefectView, RunData

if TYPE_CHECKING:
    from roadsurf.core.camera import Camera


def gps_enu_m(data: RunData) -> np.ndarray | None:
    """(N, 3) GPS fixes in ENU (alt NaN -> reference altitude), or None."""
    d = data.drive
    if d is None or d.gps is None or len(d.gps) == 0 or data.reference is None:
        return None
    alt = np.where(np.isfinite(d.gps.alt_m), d.gps.alt_m, data.reference.alt_m)
    return enu_from_lla(d.gps.lat_deg, d.gps.lon_deg, alt, data.reference)


def road_height_near(data: RunData, east_north: np.ndarray, radius_m: float = 0.5) -> float:
    """Median cloud height around a point (m, ENU up); falls back to camera height below the
    nearest pose, then 0."""
    c = data.cloud_enu_m
    if c is not None and len(c):
        near = data.cloud_tree_xy.query_ball_point(np.asarray(east_north, float)[:2], radius_m)
        if len(near) >= 3:
            z = c[near, 2]
            if data.cloud_residual_m is not None:
                z = z - data.cloud_residual_m[near]  # the road surface, not the defect floor
            return float(np.median(z))
    t = data.trajectory
    if t is not None and len(t):
        pos = t.positions_enu_m
        k = int(np.argmin(np.sum((pos[:, :2] - east_north[None, :2]) ** 2, axis=1)))
        h = float(data.drive.camera.height_m) if data.drive is not None else 0.0
        return float(pos[k, 2] - h)
    return 0.0


def defect_rings_3d(data: RunData) -> list[tuple[DefectView, np.ndarray]]:
    """(defect, (K, 3) ENU outline at the road surface) for every defect."""
    out = []
    for d in data.defects:
        z = road_height_near(data, d.centroid_enu_m)
        out.append((d, np.column_stack([d.ring_enu_m, np.full(len(d.ring_enu_m), z)])))
    return out


def project_to_image(
    world_from_cam: np.ndarray, cam: Camera, pts_enu_m: np.ndarray
) -> np.ndarray | None:
    """(K, 3) ENU points -> (K, 2) raw pixels (u right, v down), lens distortion included (the
    images shown are the raw frames); None when any point is behind the camera or none falls
    inside the image."""
    pc = transform_points(invert_pose(world_from_cam), pts_enu_m)
    if np.any(pc[:, 2] <= 1e-3):
        return None
    u, v = cam.project(pc)
    uv = np.column_stack([u, v])
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return uv if inside.any() else None


def rowcol_from_enu(data: RunData, grid: GridSpec, enu_m: np.ndarray) -> np.ndarray:
    """(N, 2|3) ENU -> (N, 2) float row, col on a raster grid in the run's export CRS."""
    enu = np.atleast_2d(np.asarray(enu_m, float))
    if enu.shape[1] == 2:
        enu = np.column_stack([enu, np.zeros(len(enu))])
    ef = data.export_frame
    xy = enu[:, :2] if ef is None else ef.utm_from_enu(enu)[:, :2]
    return grid.rowcol_from_xy(xy)
