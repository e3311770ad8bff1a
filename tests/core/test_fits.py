"""The one home of plane fits and the 2D rigid fit, on seeded synthetic points."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roadsurf.core.fits import (
    fit_plane_z,
    fit_plane_z_trimmed,
    fit_rigid_2d,
    plane_signed_distance,
    robust_plane_z,
    robust_sigma,
)


def _rot(th: float) -> np.ndarray:
    return np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])


@pytest.mark.parametrize("weighted", [False, True])
def test_rigid_fit_recovers_a_known_transform(weighted: bool) -> None:
    rng = np.random.default_rng(1)
    src = rng.uniform(-20, 20, (40, 2))
    dst = src @ _rot(-2.5).T + [103.0, -7.0] + rng.normal(0, 1e-3, (40, 2))
    fit = fit_rigid_2d(src, dst, np.full(40, 2.0) if weighted else None)
    assert fit.yaw_rad == pytest.approx(-2.5, abs=1e-4)
    assert np.abs(fit.apply(src) - dst).max() < 5e-3


def test_similarity_fit_recovers_the_scale() -> None:
    rng = np.random.default_rng(2)
    src = rng.normal(size=(30, 2))
    dst = 0.37 * src @ _rot(1.1).T + [5.0, 6.0]
    fit = fit_rigid_2d(src, dst, with_scale=True)
    assert fit.scale == pytest.approx(0.37, rel=1e-9)
    assert np.abs(fit.apply(src) - dst).max() < 1e-9
    with pytest.raises(ValueError):
        fit_rigid_2d(src, dst, np.ones(30), with_scale=True)


def test_plane_fits_ignore_a_pothole() -> None:
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1, 1, (800, 2))
    z = 0.02 * xy[:, 0] - 0.01 * xy[:, 1] + 1.5 + rng.normal(0, 5e-4, 800)
    hole = np.hypot(xy[:, 0] - 0.3, xy[:, 1]) < 0.25
    z[hole] -= 0.04
    P = np.column_stack([xy, z])
    plain = fit_plane_z(P)
    trimmed, used = fit_plane_z_trimmed(P, trim_k=3.0)
    robust = robust_plane_z(P)
    assert robust is not None
    for p in (trimmed, robust):
        assert p[2] == pytest.approx(1.5, abs=1e-3) and abs(p[0] - 0.02) < 2e-3
    assert abs(plain[2] - 1.5) > abs(trimmed[2] - 1.5)  # the plain fit is pulled down
    assert not used[hole].any()
    d = plane_signed_distance(P, trimmed)
    # a drop in z gives +d here; in camera coordinates Z grows into the road: potholes are -d
    assert np.median(d[hole]) == pytest.approx(0.04, abs=3e-3)
    assert robust_sigma(d[~hole]) == pytest.approx(5e-4, rel=0.2)


def test_fit_plane_needs_three_points() -> None:
    with pytest.raises(ValueError, match="at least 3"):
        fit_plane_z(np.zeros((2, 3)))


def test_trimmed_lstsq_drops_outliers_and_refuses_too_few_rows() -> None:
    from roadsurf.core.fits import trimmed_lstsq

    rng = np.random.default_rng(2)
    x = rng.uniform(-1, 1, 200)
    A = np.c_[np.ones_like(x), x]
    y = 0.5 + 2.0 * x + rng.normal(0, 0.01, len(x))
    y[:6] += 0.2  # a few rows 20 σ off
    fit = trimmed_lstsq(A, y, min_used=50, sigma_floor=1e-6)
    assert fit is not None
    coef, res, sig, use = fit
    assert coef == pytest.approx([0.5, 2.0], abs=0.005)
    assert not use[:6].any() and use[6:].mean() > 0.95
    assert sig == pytest.approx(0.01, rel=0.2) and res.shape == y.shape
    assert trimmed_lstsq(A, y, min_used=199, sigma_floor=1e-6) is None  # 6 rows go


def test_plane_in_camera_b_holds_the_same_points_and_side() -> None:
    from scipy.spatial.transform import Rotation

    from roadsurf.core.fits import plane_b_from_plane_a, plane_signed_distance

    rng = np.random.default_rng(4)
    R = Rotation.from_rotvec([0.05, -0.1, 0.2]).as_matrix()
    t = np.array([0.1, -0.4, 0.05])
    plane_a = np.array([0.1, -0.7, 1.3])
    P_a = rng.uniform(-1, 1, (20, 3))
    P_a[:, 2] += 1.5
    pb = plane_b_from_plane_a(plane_a, R, t)
    P_b = P_a @ R.T + t
    # signed distances (m) are the same in both frames, on the plane and off it
    assert np.allclose(plane_signed_distance(P_b, pb), plane_signed_distance(P_a, plane_a))
    # camera b looking along the plane has no z = f(x, y) form
    edge = Rotation.from_euler("x", 90, degrees=True).as_matrix()
    with pytest.raises(ValueError, match="edge-on"):
        plane_b_from_plane_a(np.array([0.0, 0.0, 1.0]), edge, np.zeros(3))
