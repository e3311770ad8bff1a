"""Where the posed frames see the road: the camera projection, each frame's road footprint,
and how much consecutive footprints overlap (the map is strips below half)."""

from __future__ import annotations

import logging

import cv2
import numpy as np

from roadsurf.io.drive import Camera
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.types import MapProducts

log = logging.getLogger(__name__)


def project(camera: Camera, X_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (..., 3) -> distorted pixel u, v (...). Z <= 0 gives NaN."""
    Z = X_cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(Z > 1e-6, X_cam[..., 0] / Z, np.nan)
        y = np.where(Z > 1e-6, X_cam[..., 1] / Z, np.nan)
    if camera.has_distortion:
        k1, k2, p1, p2, k3 = camera.dist
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = (
            x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
        )
    return camera.fx * x + camera.cx, camera.fy * y + camera.cy


def consecutive_overlap(footprints_xy_m: list[np.ndarray]) -> np.ndarray:
    """(N-1,) share of frame i's road footprint that frame i+1 also sees (0-1; NaN where a
    footprint is missing). ``footprints_xy_m``: N arrays (K, 2) of footprint points (m), e.g.
    ``footprint_enu``'s grid; each footprint is their convex hull."""
    import shapely

    hulls = [
        shapely.MultiPoint(np.asarray(f, float)).convex_hull if len(f) >= 3 else None
        for f in footprints_xy_m
    ]
    out = np.full(max(0, len(hulls) - 1), np.nan)
    for i in range(len(out)):
        a, b = hulls[i], hulls[i + 1]
        if a is not None and b is not None and a.area > 0:
            out[i] = a.intersection(b).area / a.area
    return out


def check_frame_overlap(cfg: MappingConfig, fp_grid: list[np.ndarray], prod: MapProducts) -> None:
    """Record the consecutive-frame overlap and warn when it is below ``min_frame_overlap``:
    below half, the two-view parts of consecutive pairs no longer touch and the map is strips."""
    ov = consecutive_overlap(fp_grid)
    ov = ov[np.isfinite(ov)]
    if not len(ov):
        return
    med = float(np.median(ov))
    prod.frame_overlap = {"median": round(med, 3), "p10": round(float(np.percentile(ov, 10)), 3)}
    if med < cfg.min_frame_overlap:
        msg = (
            f"consecutive frames overlap by only {med:.0%} (median; below "
            f"{cfg.min_frame_overlap:.0%}): 3D comes from the overlaps, so the map is strips "
            "with unmeasured road between them, defects there are missed and long ones are "
            "measured in pieces. Drive slower or raise the frame rate (overlap = 1 - speed / "
            "(frame rate x footprint length along the drive))"
        )
        log.warning("globalmap: %s", msg)
        prod.warnings.append(msg)


def footprint_enu(camera: Camera, W: np.ndarray, road_z: float, n: int = 5) -> np.ndarray:
    """(n*n, 3) ENU points where an n×n grid of image pixels meets the plane z = road_z."""
    u = np.linspace(0, camera.width - 1, n)
    v = np.linspace(0, camera.height - 1, n)
    U, V = np.meshgrid(u, v)
    px = np.column_stack([U.ravel(), V.ravel()]).astype(np.float64)
    if camera.has_distortion:
        und = cv2.undistortPoints(
            px.reshape(-1, 1, 2), camera.K, np.asarray(camera.dist, float)
        ).reshape(-1, 2)
    else:
        und = np.column_stack(
            [(px[:, 0] - camera.cx) / camera.fx, (px[:, 1] - camera.cy) / camera.fy]
        )
    rays = np.column_stack([und, np.ones(len(und))]) @ W[:3, :3].T
    c = W[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (road_z - c[2]) / rays[:, 2]
    lam = np.where(np.isfinite(lam) & (lam > 0), lam, np.nan)
    pts = c + lam[:, None] * rays
    return pts[np.all(np.isfinite(pts), axis=1)]
