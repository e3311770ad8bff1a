"""The one Camera: distortion round trips, projection against OpenCV, footprints."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from roadsurf.core.camera import RENDER_UNDISTORT_CRITERIA, Camera

CAM = Camera(640, 480, 600.0, 610.0, 319.5, 239.5, 1.2, 15.0, (-0.21, 0.05, 1e-3, -5e-4, 0.0))
PIN = Camera(640, 480, 600.0, 600.0, 319.5, 239.5, 1.2, 15.0)


def _grid(cam: Camera) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, 9), np.linspace(0, cam.height - 1, 7))
    return np.column_stack([u.ravel(), v.ravel()])


def test_project_matches_opencv() -> None:
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-0.6, 0.6, (50, 2)), rng.uniform(1.0, 2.0, 50)])
    u, v = CAM.project(X)
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), CAM.K, CAM.dist_array)
    assert np.abs(np.column_stack([u, v]) - ref.reshape(-1, 2)).max() < 1e-9
    u, v = CAM.project(np.array([[0.1, 0.1, -1.0]]))
    assert np.isnan(u).all() and np.isnan(v).all()


def test_distort_undistort_round_trip() -> None:
    ideal = _grid(CAM) * 0.8 + 60
    raw = CAM.distort_px(ideal)
    assert np.abs(raw - ideal).max() > 1.0  # the lens really bends
    assert np.abs(CAM.undistort_px(raw) - ideal).max() < 0.05  # OpenCV's 5 iterations
    n = CAM.normalised_from_raw_px(raw, criteria=RENDER_UNDISTORT_CRITERIA)
    assert np.abs(n - CAM.normalised_from_px(ideal)).max() < 1e-8
    assert PIN.distort_px(ideal) is ideal and np.array_equal(PIN.undistort_px(ideal), ideal)


def test_nadir_footprints_are_the_expected_rectangle() -> None:
    W = np.eye(4)
    W[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking straight down
    W[:3, 3] = [10.0, 20.0, 1.2]
    corners = PIN.footprint_corners_enu(W)
    assert corners is not None
    half_w, half_h = 1.2 * 320 / 600, 1.2 * 240 / 600
    assert np.allclose(np.abs(corners - [10, 20]), [half_w, half_h])
    grid = PIN.footprint_grid_enu(W, road_z=0.0, n=3)
    assert grid.shape == (9, 3) and np.allclose(grid[:, 2], 0.0)
    assert np.allclose(grid[4, :2], [10.0 + 0.5 / 600 * 1.2 * 0, 20.0], atol=2e-3)
    W_up = W.copy()
    W_up[:3, :3] = np.eye(3)  # looking up: no footprint
    assert PIN.footprint_corners_enu(W_up) is None
    assert len(PIN.footprint_grid_enu(W_up, road_z=0.0)) == 0


def test_ground_px() -> None:
    assert PIN.ground_px_m() == pytest.approx(0.002)
