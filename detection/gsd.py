"""Ground size of image pixels where detection turns pixels into metres or back.

A nadir camera over a flat road maps it with one scale (h / f everywhere); a tilted one (45° in
real photographs) sees a pixel near the horizon cover several times the ground of one near its
feet. Detection therefore asks the camera per pixel (``Camera.ground_px_m_at``, for a level
vehicle at the camera's height) wherever a length or an area is measured in the image
(``ground_px_m_raw``), and bins image positions on a virtual nadir view where a uniform ground
grid is needed (``NadirView``). For the nadir camera (mount unknown, zero, or turned about the
optical axis only) both reduce exactly to the nominal ``Camera.ground_px_m``.
"""

from __future__ import annotations

import math

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.geometry import rotation_b_from_a


def ground_px_m_raw(camera: Camera, px_raw: np.ndarray, fallback_m: float) -> np.ndarray:
    """(N,) ground size of a pixel (m/px) at raw image pixels (N, 2); ``fallback_m`` where the
    pixel's ray misses the road (above the horizon)."""
    px = np.asarray(px_raw, float).reshape(-1, 2)
    if len(px) == 0:
        return np.zeros(0)
    g = camera.ground_px_m_at(camera.undistort_px(px))
    return np.where(np.isfinite(g) & (g > 0), g, fallback_m)


class NadirView:
    """Ideal pixels of the camera re-expressed as pixels of a virtual camera at the same place
    turned to look straight down (the minimal rotation, no turn about the optical axis), where
    the road has one scale, ``m_per_px``. The nadir camera is its own nadir view."""

    def __init__(self, camera: Camera) -> None:
        down = camera.vehicle_from_cam[2]  # vehicle z (down) in camera coordinates
        self.nadir = bool(np.array_equal(down, np.array([0.0, 0.0, 1.0])))
        self.camera = camera
        if self.nadir:
            self.R = np.eye(3)
            self.m_per_px = camera.ground_px_m()
        else:
            self.R = rotation_b_from_a(np.asarray(down, float), np.array([0.0, 0.0, 1.0]))
            self.m_per_px = camera.height_m / math.sqrt(camera.fx * camera.fy)

    def px(self, px_ideal: np.ndarray) -> np.ndarray:
        """(N, 2) ideal pixels -> (N, 2) nadir-view pixels (NaN for rays that miss the road)."""
        p = np.asarray(px_ideal, float).reshape(-1, 2)
        if self.nadir:
            return p
        n = self.camera.normalised_from_px(p)
        r = np.c_[n, np.ones(len(n))] @ self.R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(r[:, 2] > 1e-9, r[:, 0] / r[:, 2], np.nan)
            y = np.where(r[:, 2] > 1e-9, r[:, 1] / r[:, 2], np.nan)
        return np.c_[self.camera.fx * x + self.camera.cx, self.camera.fy * y + self.camera.cy]
