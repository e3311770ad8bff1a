"""The SfM baseline's own fits: a RANSAC plane through a camera's 3D points and the robust 2D
rigid/similarity (Umeyama) fit of camera centres to GPS.

They differ from the stages' fits (``roadsurf.core.fits``: planes Z = p0 X + p1 Y + p2 by least
squares, the closed-form 2D rigid fit) in algorithm and results, so they stay here.
"""

from __future__ import annotations

import math

import numpy as np

from roadsurf.core.geometry import check_shape


def _fit_plane_lsq(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through (N, 3) points: unit normal n (3,) and offset d, n·x + d = 0."""
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    n = vt[-1]
    return n, -float(n @ c)


def fit_plane_ransac(
    pts: np.ndarray, thr: float, iterations: int, rng: np.random.Generator
) -> tuple[np.ndarray, float, np.ndarray]:
    """Robust plane: RANSAC (MSAC score) then least squares on the inliers.

    pts: (N, 3) points, thr: inlier distance (same unit). Returns (normal (3,), d, inlier mask (N,)).
    """
    pts = check_shape("pts", pts, (None, 3))
    n_pts = len(pts)
    if n_pts < 3:
        raise ValueError("a plane needs at least 3 points")
    best_cost, best = math.inf, None
    for _ in range(iterations):
        s = pts[rng.choice(n_pts, 3, replace=False)]
        nrm = np.cross(s[1] - s[0], s[2] - s[0])
        ln = np.linalg.norm(nrm)
        if ln < 1e-12:
            continue
        nrm /= ln
        r = np.abs(pts @ nrm - nrm @ s[0])
        cost = float(np.minimum(r, thr).sum())
        if cost < best_cost:
            best_cost, best = cost, (nrm, -float(nrm @ s[0]))
    if best is None:
        n, d = _fit_plane_lsq(pts)
    else:
        n, d = best
    inl = np.abs(pts @ n + d) < thr
    for _ in range(2):  # refine on the inliers
        if inl.sum() < 3:
            break
        n, d = _fit_plane_lsq(pts[inl])
        inl = np.abs(pts @ n + d) < thr
    return n, d, inl


def fit_2d_transform(
    src: np.ndarray, dst: np.ndarray, with_scale: bool
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares 2D rigid/similarity (Umeyama): dst ≈ s R src + t.

    src, dst: (N, 2) metres. Returns (R (2, 2), t (2,), s)."""
    src = check_shape("src", src, (None, 2))
    dst = check_shape("dst", dst, (None, 2))
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    u, sv, vt = np.linalg.svd(cov)
    sign = np.diag([1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    R = u @ sign @ vt
    var_s = float((a**2).sum() / len(src))
    s = float(np.trace(np.diag(sv) @ sign) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def robust_fit_2d(
    src: np.ndarray, dst: np.ndarray, with_scale: bool, k: float
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Iteratively reweighted (trimmed) 2D fit: refit without pairs whose residual exceeds
    k robust sigmas (MAD). Returns (R, t, s, inlier mask (N,))."""
    inl = np.ones(len(src), bool)
    R, t, s = fit_2d_transform(src, dst, with_scale)
    for _ in range(5):
        r = np.linalg.norm(dst - (s * src @ R.T + t), axis=1)
        sigma = 1.4826 * float(np.median(r[inl])) + 1e-9
        new = r <= max(k * sigma, 1e-6)
        if new.sum() < 2 or np.array_equal(new, inl):
            break
        inl = new
        R, t, s = fit_2d_transform(src[inl], dst[inl], with_scale)
    return R, t, s, inl
