"""Tiny seeded synthetic image pairs of a textured plane (no simulator needed)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from roadsurf.core.camera import Camera
from roadsurf.core.geometry import rotation_from_euler_xyz


def make_camera(width: int = 512, height: int = 384, f: float = 480.0, h: float = 1.1) -> Camera:
    return Camera(width, height, f, f, width / 2, height / 2, h, 10.0)


def texture(shape: tuple[int, int], seed: int) -> np.ndarray:
    """Multi-scale random texture, uint8 (rich in SIFT features, like asphalt)."""
    rng = np.random.default_rng(seed)
    img = np.zeros(shape, np.float32)
    for s in (1.0, 2.0, 4.0, 8.0):
        n = rng.normal(0, 1, shape).astype(np.float32)
        img += s * cv2.GaussianBlur(n, (0, 0), s)
    img = (img - img.min()) / (img.max() - img.min() + 1e-9)
    return (img * 255).astype(np.uint8)


def render_pair(
    cam: Camera,
    t_m: tuple[float, float, float] = (0.1, 0.015, 0.0),
    theta_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Images a, b of the plane Z = h in camera a; X_b = R X_a + t."""
    pad = cam.width
    big = texture((cam.height + 2 * pad, cam.width + 2 * pad), seed)
    K = cam.K
    R = rotation_from_euler_xyz(*np.radians(theta_deg))
    n = np.array([0.0, 0.0, 1.0])
    Hn = R + np.outer(np.asarray(t_m), n) / cam.height_m
    H_b_from_a = K @ Hn @ np.linalg.inv(K)
    shift = np.array([[1, 0, pad], [0, 1, pad], [0, 0, 1.0]])  # big -> a pixels: subtract pad
    img_a = big[pad : pad + cam.height, pad : pad + cam.width].copy()
    M = H_b_from_a @ np.linalg.inv(shift)  # big pixels -> b pixels
    img_b = cv2.warpPerspective(big, M, (cam.width, cam.height), flags=cv2.INTER_LINEAR)
    return img_a, img_b


@pytest.fixture
def cam() -> Camera:
    return make_camera()
