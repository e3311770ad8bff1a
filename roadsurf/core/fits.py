"""The one place for robust statistics, plane fits and the 2D rigid fit.

Planes are ``Z = p0 X + p1 Y + p2`` (dissertation eq. 3.31) in metres, in whatever frame the
points are given (camera or world); distances are signed, negative below the road (eq. 3.32).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from roadsurf.core.geometry import check_shape

MAD_TO_SIGMA = 1.4826  # σ of a normal distribution from its median absolute deviation
# median of a Rayleigh(σ = 1) variable (≈ 1.1774): the norm of a 2D error with σ per axis, or a
# small angle between two noisy directions, has median RAYLEIGH_MEDIAN σ
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


def robust_sigma(values: np.ndarray) -> float:
    """σ estimated as 1.4826 · MAD (robust to a minority of outliers); NaN for empty input.
    Non-finite values are ignored."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan")
    return float(MAD_TO_SIGMA * np.median(np.abs(v - np.median(v))))


def trimmed_lstsq(
    A: np.ndarray,
    y: np.ndarray,
    min_used: int,
    sigma_floor: float,
    k: float = 3.0,
    iterations: int = 3,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray] | None:
    """Least squares y ≈ A coef, refitted ``iterations`` times on the rows within ``k`` robust
    σ (MAD, at least ``sigma_floor``) of the previous fit. A (N, P), y (N,). Returns (coef (P,),
    residuals of every row (N,), σ, rows kept (N,) bool), or None once fewer than ``min_used``
    rows stay."""
    use = np.ones(len(y), bool)
    coef, res, sig = np.zeros(A.shape[1]), np.zeros(len(y)), sigma_floor
    for _ in range(iterations):
        coef = np.linalg.lstsq(A[use], y[use], rcond=None)[0]
        res = y - A @ coef
        sig = max(robust_sigma(res[use]), sigma_floor)
        use = np.abs(res) <= k * sig
        if use.sum() < min_used:
            return None
    return coef, res, sig, use


# ---------------------------------------------------------------------------------- planes
def fit_plane_z(points_m: np.ndarray) -> np.ndarray:
    """Least-squares plane Z = p0 X + p1 Y + p2 through (N, 3) points (N >= 3); returns (3,)."""
    P = check_shape("points_m", points_m, (None, 3))
    if P.shape[0] < 3:
        raise ValueError(f"fit_plane_z: need at least 3 points, got {P.shape[0]}")
    A = np.column_stack([P[:, 0], P[:, 1], np.ones(len(P))])
    p, *_ = np.linalg.lstsq(A, P[:, 2], rcond=None)
    return p


def fit_plane_z_trimmed(
    X: np.ndarray, trim_k: float = 0.0, iterations: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane (eq. 3.31) refitted without points whose VERTICAL residual is more
    than ``trim_k`` robust sigmas from the median (so potholes do not tilt the road plane).

    X: (N, 3) metres. trim_k <= 0 is one plain fit. Stops when fewer than 3 points would stay
    or the inlier set no longer changes. Returns (p (3,), used mask (N,))."""
    X = check_shape("X", X, (None, 3))
    used = np.ones(X.shape[0], dtype=bool)
    p = np.full(3, np.nan)
    for _ in range(max(1, iterations if trim_k > 0 else 1)):
        A = np.column_stack([X[used, 0], X[used, 1], np.ones(int(used.sum()))])
        p = np.linalg.lstsq(A, X[used, 2], rcond=None)[0]
        if trim_k <= 0:
            break
        r = X[:, 2] - (p[0] * X[:, 0] + p[1] * X[:, 1] + p[2])
        s = MAD_TO_SIGMA * np.median(np.abs(r[used] - np.median(r[used]))) + 1e-12
        new = np.abs(r - np.median(r[used])) <= trim_k * s
        if new.sum() < 3 or np.array_equal(new, used):
            break
        used = new
    return p, used


def plane_signed_distance(points_m: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """(N,) d_i = (p0 X + p1 Y - Z + p2) / sqrt(p0² + p1² + 1) (eq. 3.32); negative below."""
    P = check_shape("points_m", points_m, (None, 3))
    p0, p1, p2 = check_shape("plane", plane, (3,))
    return (p0 * P[:, 0] + p1 * P[:, 1] - P[:, 2] + p2) / np.sqrt(p0 * p0 + p1 * p1 + 1.0)


def plane_b_from_plane_a(
    plane_a: np.ndarray, R_b_from_a: np.ndarray, t_b_from_a_m: np.ndarray
) -> np.ndarray:
    """The plane z = p0 x + p1 y + p2 (3,) of camera a's frame as the same plane in camera b's
    (X_b = R X_a + t, m): (3,) p' with the same sign of ``plane_signed_distance`` on either
    side. Raises ValueError when camera b sees the plane edge-on (its z axis in the plane)."""
    p = check_shape("plane_a", np.asarray(plane_a, float), (3,))
    R = check_shape("R_b_from_a", np.asarray(R_b_from_a, float), (3, 3))
    t = check_shape("t_b_from_a_m", np.asarray(t_b_from_a_m, float), (3,))
    m = R @ np.array([-p[0], -p[1], 1.0])  # the normal (-p0, -p1, 1) in camera b
    if m[2] <= 1e-9 * np.linalg.norm(m):
        raise ValueError("camera b sees the plane edge-on or from behind: no z = f(x, y) form")
    return np.array([-m[0] / m[2], -m[1] / m[2], (p[2] + m @ t) / m[2]])


def camera_plane_distance(p: np.ndarray) -> float:
    """d_c = |p2| / sqrt(p0² + p1² + 1) (eq. 3.33): the camera's distance to the plane, when
    the plane is in camera coordinates."""
    return float(abs(p[2]) / np.sqrt(p[0] ** 2 + p[1] ** 2 + 1))


def robust_plane_z(points_m: np.ndarray, iterations: int = 3) -> np.ndarray | None:
    """Plane (3,) through road points (N, 3), refit without the points beyond 3 σ (MAD) of the
    previous fit's PERPENDICULAR distances, ``iterations`` fits in all; None with fewer than 10
    points."""
    P = check_shape("points_m", np.asarray(points_m, float), (None, 3))
    keep = np.ones(len(P), bool)
    plane = None
    for _ in range(iterations):
        if keep.sum() < 10:
            return plane
        plane = fit_plane_z(P[keep])
        d = plane_signed_distance(P, plane)
        s = max(robust_sigma(d[keep]), 1e-4)
        keep = np.abs(d - np.median(d[keep])) <= 3.0 * s
    return plane


# ---------------------------------------------------------------------------------- 2D rigid
@dataclass(frozen=True)
class Rigid2D:
    """dst ≈ s R @ src + t, with R a rotation by ``yaw_rad`` (counter-clockwise) and s the
    scale (1 for a rigid fit)."""

    yaw_rad: float
    R: np.ndarray  # (2, 2)
    t: np.ndarray  # (2,) metres
    scale: float = 1.0

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) -> (N, 2)."""
        return self.scale * xy @ self.R.T + self.t


def fit_rigid_2d(
    src: np.ndarray,
    dst: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    with_scale: bool = False,
) -> Rigid2D:
    """Least-squares 2D rigid transform dst ≈ R src + t between (N, 2) point sets (metres).

    Closed form: the rotation angle is atan2 of the cross-covariance's antisymmetric and
    symmetric parts, exact in 2D and free of SVD reflection cases. ``weights`` (N,), if given,
    weigh each pair (normalised to sum 1). ``with_scale`` (unweighted only) also fits the
    scale s of a similarity dst ≈ s R src + t (Umeyama's estimate, in closed form)."""
    src = check_shape("src", np.asarray(src, float), (None, 2))
    dst = check_shape("dst", np.asarray(dst, float), (None, 2))
    if weights is None:
        ms, md = src.mean(0), dst.mean(0)
        S = (src - ms).T @ (dst - md)
        yaw = math.atan2(S[0, 1] - S[1, 0], S[0, 0] + S[1, 1])
        R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        if not with_scale:
            return Rigid2D(yaw, R, md - ms @ R.T)
        var = float(((src - ms) ** 2).sum())
        s = math.hypot(S[0, 0] + S[1, 1], S[0, 1] - S[1, 0]) / var if var > 0 else 1.0
        return Rigid2D(yaw, R, md - s * ms @ R.T, s)
    if with_scale:
        raise ValueError("fit_rigid_2d: with_scale needs an unweighted fit")
    w = weights / weights.sum()
    ms, md = w @ src, w @ dst
    S = ((src - ms) * w[:, None]).T @ (dst - md)
    yaw = math.atan2(S[0, 1] - S[1, 0], S[0, 0] + S[1, 1])
    R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    return Rigid2D(yaw, R, md - R @ ms)


# ---------------------------------------------------------------------- planes, normal form
def fit_plane_tls(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares plane through (N, 3) points (N >= 3): unit normal n (3,) and offset
    d (same unit as the points) with n·x + d = 0, minimising PERPENDICULAR distances (SVD of
    the centred points). Unlike ``fit_plane_z`` it has no preferred axis, so it suits point
    clouds in an arbitrary frame (e.g. a COLMAP model)."""
    pts = check_shape("points", points, (None, 3))
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    n = vt[-1]
    return n, -float(n @ c)


def fit_plane_ransac(
    points: np.ndarray, thr: float, iterations: int, rng: np.random.Generator
) -> tuple[np.ndarray, float, np.ndarray]:
    """Robust plane in normal form: RANSAC over 3-point samples with the MSAC score
    (sum of min(distance, thr)), then two total-least-squares refits on the inliers.

    points: (N, 3), thr: inlier distance (same unit), ``iterations`` samples drawn from
    ``rng``. Returns (unit normal (3,), d, inlier mask (N,)) with n·x + d = 0."""
    pts = check_shape("points", points, (None, 3))
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
        n, d = fit_plane_tls(pts)
    else:
        n, d = best
    inl = np.abs(pts @ n + d) < thr
    for _ in range(2):  # refine on the inliers
        if inl.sum() < 3:
            break
        n, d = fit_plane_tls(pts[inl])
        inl = np.abs(pts @ n + d) < thr
    return n, d, inl
