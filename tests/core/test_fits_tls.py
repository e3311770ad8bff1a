"""Planes in normal form (core.fits.fit_plane_tls / fit_plane_ransac), on seeded points."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roadsurf.core.fits import fit_plane_ransac, fit_plane_tls


def _unit(v: list[float]) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def test_tls_plane_is_exact_on_a_tilted_plane_and_perpendicular() -> None:
    rng = np.random.default_rng(0)
    n_true = _unit([0.3, -0.2, 0.9])
    # points on n·x = 2 spread along two in-plane directions
    u = _unit(np.cross(n_true, [1.0, 0.0, 0.0]).tolist())
    v = np.cross(n_true, u)
    ab = rng.uniform(-5, 5, (200, 2))
    pts = 2.0 * n_true + ab[:, :1] * u + ab[:, 1:] * v
    n, d = fit_plane_tls(pts)
    assert abs(np.linalg.norm(n) - 1) < 1e-12
    s = np.sign(n @ n_true)
    assert np.allclose(s * n, n_true, atol=1e-12) and s * d == pytest.approx(-2.0, abs=1e-12)
    # a vertical wall: a Z = f(X, Y) fit cannot represent it, the total least squares can
    wall = np.column_stack([np.full(50, 1.5), rng.uniform(-1, 1, 50), rng.uniform(0, 2, 50)])
    n, d = fit_plane_tls(wall)
    assert abs(abs(n[0]) - 1) < 1e-12 and abs(abs(d) - 1.5) < 1e-12


def test_tls_plane_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="points"):
        fit_plane_tls(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="at least 3"):
        fit_plane_ransac(np.zeros((2, 3)), 0.1, 10, np.random.default_rng(0))


def test_plane_ransac_ignores_pothole_and_outliers() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1, 1, (600, 2))
    z = 0.02 * xy[:, 0] - 0.01 * xy[:, 1] + 3.0 + rng.normal(0, 0.001, 600)
    z[:60] -= 0.05  # a pothole
    z[60:80] += rng.uniform(0.2, 1.0, 20)  # gross outliers
    pts = np.column_stack([xy, z])
    n, d, inl = fit_plane_ransac(pts, 0.01, 200, rng)
    n_true = _unit([0.02, -0.01, -1.0])
    assert abs(abs(n @ n_true) - 1) < 1e-4
    assert not inl[:80].any() and inl[80:].mean() > 0.98
    # distance of (0, 0, 0) to the plane z = ... + 3
    assert abs(abs(d) - 3.0 / math.sqrt(1 + 0.02**2 + 0.01**2)) < 0.005


def test_plane_ransac_is_reproducible_and_falls_back_on_degenerate_samples() -> None:
    rng = np.random.default_rng(4)
    pts = np.column_stack([rng.uniform(-1, 1, (100, 2)), rng.normal(0, 1e-3, 100)])
    a = fit_plane_ransac(pts, 0.01, 50, np.random.default_rng(9))
    b = fit_plane_ransac(pts, 0.01, 50, np.random.default_rng(9))
    assert np.array_equal(a[0], b[0]) and a[1] == b[1] and np.array_equal(a[2], b[2])
    # collinear points: every 3-point sample is degenerate; the TLS fallback still answers
    line = np.column_stack([np.linspace(0, 1, 10), np.zeros(10), np.zeros(10)])
    n, d, inl = fit_plane_ransac(line, 0.01, 20, np.random.default_rng(0))
    assert abs(n[0]) < 1e-12 and abs(d) < 1e-12 and inl.all()
