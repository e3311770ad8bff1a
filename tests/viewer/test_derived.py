"""Projection of map points into the raw frames the viewer shows."""

from __future__ import annotations

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.geometry import rotation_from_euler_xyz
from roadsurf.viewer.derived import project_to_image


def _pose(rng: np.random.Generator) -> np.ndarray:
    """A camera 1.1 m above the road looking down (z down), slightly tilted, any heading."""
    W = np.eye(4)
    W[:3, :3] = rotation_from_euler_xyz(
        np.pi + rng.normal(0, 0.03), rng.normal(0, 0.03), rng.uniform(0, 2 * np.pi)
    )
    W[:3, 3] = [rng.normal(0, 3), rng.normal(0, 3), 1.1]
    return W


def test_projection_includes_lens_distortion_as_opencv() -> None:
    cam = Camera(
        width=640, height=480, fx=600.0, fy=605.0, cx=319.5, cy=239.5, height_m=1.1, fps=15.0,
        dist=(-0.25, 0.08, 0.001, -0.001, 0.01),
    )  # fmt: skip
    rng = np.random.default_rng(3)
    for _ in range(5):
        W = _pose(rng)
        pts = np.column_stack([W[:2, 3] + rng.normal(0, 0.3, (30, 2)), rng.normal(0, 0.01, 30)])
        uv = project_to_image(W, cam, pts)
        assert uv is not None
        Wi = np.linalg.inv(W)
        rvec, _ = cv2.Rodrigues(Wi[:3, :3])
        ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, Wi[:3, 3], cam.K, cam.dist_array)
        np.testing.assert_allclose(uv, ref.reshape(-1, 2), rtol=0, atol=1e-6)
        # the distortion is large here: the pinhole projection would be pixels off
        pc = (pts - W[:3, 3]) @ W[:3, :3]
        pinhole = (pc @ cam.K.T)[:, :2] / pc[:, 2:3]
        assert np.abs(pinhole - uv).max() > 1.0


def test_points_behind_the_camera_give_none() -> None:
    cam = Camera(640, 480, 600.0, 600.0, 319.5, 239.5, 1.1, 15.0)
    W = _pose(np.random.default_rng(0))
    above = np.array([[W[0, 3], W[1, 3], 5.0]])  # 5 m up: behind a downward camera
    assert project_to_image(W, cam, above) is None
