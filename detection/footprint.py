"""Ground footprints of frames (which part of the road each image saw)."""

from __future__ import annotations

import numpy as np

from roadsurf.core.geometry import check_shape
from roadsurf.io.drive import Camera


def footprint_enu(world_from_cam: np.ndarray, camera: Camera) -> np.ndarray | None:
    """(4, 2) ENU east/north corners of the image footprint on the road plane, or None.

    The road is taken as the horizontal plane camera.height_m below the camera centre; image
    corners are cast as rays (distortion ignored: the footprint is used for coverage).
    """
    T = check_shape("world_from_cam", np.asarray(world_from_cam, float), (4, 4))
    w, h = camera.width, camera.height
    uv = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    rays = np.linalg.solve(camera.K, np.column_stack([uv, np.ones(4)]).T)  # (3, 4)
    rays_w = T[:3, :3] @ rays
    c = T[:3, 3]
    if np.any(rays_w[2] >= -1e-9):
        return None
    s = -camera.height_m / rays_w[2]
    pts = c[:, None] + rays_w * s
    return pts[:2].T.copy()
