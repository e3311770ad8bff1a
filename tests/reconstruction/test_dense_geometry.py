"""Plane + parallax relation of the dense height (reconstruction.dense.geometry) against
triangulation: a point at height η seen by two cameras, image b warped onto a by the road
homography, lands on the epipolar line through a's pixel at exactly the parallax the model gives,
and the model's inverse gives η back."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from roadsurf.core.errors import RoadsurfError
from roadsurf.reconstruction.dense.geometry import PlaneParallax, plane_normal_distance

K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])


def _pair(rng: np.random.Generator, forward_z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    R = cv2.Rodrigues(rng.normal(0, 0.03, 3))[0]
    C_b = np.array([0.03, -0.4, forward_z])  # b ahead (image up = -y), forward_z towards the road
    t = -R @ C_b
    plane = np.array([0.03, -0.06, 1.1])
    return R, t, plane


@pytest.mark.parametrize("forward_z", [0.0, 0.15, -0.2])
def test_parallax_matches_triangulation(forward_z: float) -> None:
    rng = np.random.default_rng(3)
    R, t, plane = _pair(rng, forward_z)
    pp = PlaneParallax.from_pair(R, t, plane, K)
    u, v = rng.uniform(0, 640, 300), rng.uniform(0, 480, 300)
    eta = rng.uniform(-0.1, 0.05, 300)
    X = pp.points_cam_a(eta, u, v)
    assert np.allclose(pp.h_a - X @ pp.n, eta, atol=1e-12)
    # project into b, warp back with H⁻¹ (where b's pixel lands in the plane-warped image)
    xb = (X @ R.T + t) @ K.T
    xb = np.column_stack([xb[:, :2] / xb[:, 2:], np.ones(300)])
    xw = xb @ np.linalg.inv(pp.H).T
    d = xw[:, :2] / xw[:, 2:] - np.column_stack([u, v])
    wx, wy, _ = pp.direction(u, v)
    s = d[:, 0] * wx + d[:, 1] * wy
    assert np.abs(-d[:, 0] * wy + d[:, 1] * wx).max() < 1e-9  # on the epipolar line
    assert np.allclose(pp.shift_from_height(eta, u, v), s, atol=1e-9)
    assert np.allclose(pp.height_from_shift(s, u, v), eta, atol=1e-12)
    # points above the road move towards +ŵ, below towards -ŵ
    assert np.all(np.sign(s[np.abs(eta) > 1e-3]) == np.sign(eta[np.abs(eta) > 1e-3]))
    e = 1e-4
    num = (pp.height_from_shift(s + e, u, v) - pp.height_from_shift(s - e, u, v)) / (2 * e)
    assert np.allclose(pp.dheight_dshift(s, u, v), num, rtol=1e-6)


def test_road_homography_maps_road_points() -> None:
    rng = np.random.default_rng(4)
    R, t, plane = _pair(rng, 0.05)
    pp = PlaneParallax.from_pair(R, t, plane, K)
    u, v = rng.uniform(0, 640, 50), rng.uniform(0, 480, 50)
    X = pp.points_cam_a(np.zeros(50), u, v)
    xb = (X @ R.T + t) @ K.T
    xa = np.column_stack([u, v, np.ones(50)]) @ pp.H.T
    assert np.allclose(xa[:, :2] / xa[:, 2:], xb[:, :2] / xb[:, 2:], atol=1e-9)


def test_scaled_model_scales_the_parallax() -> None:
    rng = np.random.default_rng(5)
    pp = PlaneParallax.from_pair(*_pair(rng, 0.1), K)
    u, v = rng.uniform(0, 640, 40), rng.uniform(0, 480, 40)
    eta = rng.uniform(-0.08, 0.04, 40)
    half = pp.scaled(0.5)
    s_half = half.shift_from_height(eta, (u + 0.5) * 0.5 - 0.5, (v + 0.5) * 0.5 - 0.5)
    assert np.allclose(s_half, 0.5 * pp.shift_from_height(eta, u, v), atol=1e-9)


def test_plane_conventions_and_refusals() -> None:
    n, d = plane_normal_distance(np.array([0.0, 0.0, 1.2]))
    assert np.allclose(n, [0, 0, 1]) and d == pytest.approx(1.2)
    with pytest.raises(RoadsurfError, match="not in front"):
        plane_normal_distance(np.array([0.0, 0.0, np.nan]))
    with pytest.raises(RoadsurfError, match="baseline"):
        PlaneParallax.from_pair(np.eye(3), np.zeros(3), np.array([0, 0, 1.1]), K)
