"""A rolling-shutter pair's off-plane parallax is that of the rows' baseline s_b - s_a, not the
pair's (reconstruction.dense.rolling.baseline_share, issue 28): an off-plane point is followed
through the resampling that the dense matching does, its parallax read off, and its height
recovered with and without the share."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roadsurf.core.camera import Camera
from roadsurf.core.rolling import solve_rows
from roadsurf.reconstruction.dense.geometry import PlaneParallax
from roadsurf.reconstruction.dense.rolling import baseline_share, raw_px_from_plane_px
from roadsurf.reconstruction.rolling_shutter import poses_at

# 6 m/s at 15 fps, nadir camera 1.1 m up, 30 ms readout: the road moves ~109 px down the image
# between the frames, so a point is read ~0.45 x 109 / 240 = 20 % later in b than in a
CAM = dataclasses.replace(Camera(320, 240, 300.0, 300.0, 159.5, 119.5, 1.1, 15.0), readout_s=0.03)
DT = 1 / 15
R = np.eye(3)
T = np.array([0.0, 0.4, 0.0])  # X_b = X_a + t
PLANE = np.array([0.0, 0.0, 1.1])  # z = 1.1 m in camera a


def _raw_of_point(X: np.ndarray, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """Raw pixels where frame 0 (a) or 1 (b) saw camera-a points X (N, 3), each from its row."""

    def at_row(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = frame + CAM.readout_s / DT * np.nan_to_num(v) / CAM.height
        Rs, ts = poses_at(R, T, s)
        return CAM.project(np.einsum("nij,nj->ni", Rs, X) + ts)

    return solve_rows(at_row, (len(X),))


def _grid_px_of_raw(ur: np.ndarray, vr: np.ndarray, frame: int) -> np.ndarray:
    """The grid pixels (N, 2) that the resampling reads from raw pixels (ur, vr) of a frame
    (``raw_px_from_plane_px`` inverted by a fixed point: it is about a shift plus a stretch)."""
    q = np.column_stack([ur, vr]).astype(float)
    for _ in range(60):
        u, v = raw_px_from_plane_px(q[:, 0], q[:, 1], CAM, R, T, PLANE, DT, frame)
        q = q + np.column_stack([ur - u, vr - v])
    return q


@pytest.mark.parametrize("eta", [-0.05, 0.03])
def test_off_plane_parallax_is_the_rows_baseline(eta: float) -> None:
    # points eta above the plane (negative: a pothole), seen by pixels of image a's grid
    u0 = np.array([100.0, 160.0, 220.0])
    v0 = np.array([60.0, 120.0, 150.0])
    X = np.column_stack([(u0 - CAM.cx) / CAM.fx, (v0 - CAM.cy) / CAM.fy, np.ones(3)])
    X = X * (PLANE[2] - eta)
    ua, va = _raw_of_point(X, 0)
    ub, vb = _raw_of_point(X, 1)
    qa, qb = _grid_px_of_raw(ua, va, 0), _grid_px_of_raw(ub, vb, 1)
    pp = PlaneParallax.from_pair(R, T, PLANE, CAM.K)
    wx, wy, nw = pp.direction(qa[:, 0], qa[:, 1])
    shift = (qb[:, 0] - qa[:, 0]) * wx + (qb[:, 1] - qa[:, 1]) * wy
    plain = pp.height_from_shift(shift, qa[:, 0], qa[:, 1], nw)
    # the share as the matching has it: the rows that saw the plane point behind pixel qa
    rows = [raw_px_from_plane_px(qa[:, 0], qa[:, 1], CAM, R, T, PLANE, DT, k)[1] for k in (0, 1)]
    f = baseline_share(rows[0], rows[1], CAM, DT)
    fixed = pp.height_from_shift(shift / f, qa[:, 0], qa[:, 1], nw)
    assert np.all(f > 1.15)  # b reads the point ~20 % of the motion later than a
    # the plain heights are scaled by the share, divided by it they are the true ones (to the
    # second order: the point's own rows differ from its plane point's by its parallax)
    assert np.all(np.abs(plain / eta - f) < 0.03)
    assert np.all(np.abs(fixed / eta - 1) < 0.02)
    assert np.all(np.abs(fixed / eta - 1) < 0.1 * np.abs(plain / eta - 1))


def test_a_global_shutter_has_no_share() -> None:
    gs = dataclasses.replace(CAM, readout_s=0.0)
    assert np.allclose(baseline_share(np.array([0.0, 200.0]), np.array([150.0, 10.0]), gs, DT), 1)
