"""Recursive plane fit of one pair's points (dissertation eq. 4.8-4.10).

Points are in camera-a coordinates (x right, y backward, z down, metres); the road plane is
Z = p0 X + p1 Y + p2 and the signed distance d_i is negative below the road (further from the
camera), matching ``PairResult.plane_dist_m``. The plane fits and robust σ themselves are
``roadsurf.core.fits``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA, fit_plane_z, plane_signed_distance, robust_sigma
from roadsurf.core.geometry import check_shape
from roadsurf.detection.config import PlaneFitConfig


def nanmedian_last(a: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN, NaN where a row has no finite value: the same
    values as ``np.nanmedian(a, axis=-1)``, without its per-row masked-array path and warnings
    (10-50x faster on the many short rows of sliding windows). a: (..., K) float."""
    a = np.asarray(a, float)
    s = np.sort(a, axis=-1)  # NaN sort last
    n = np.isfinite(a).sum(axis=-1)
    lo = np.maximum((n - 1) // 2, 0)[..., None]
    hi = np.maximum(n // 2, 0)[..., None]
    m = 0.5 * (np.take_along_axis(s, lo, -1) + np.take_along_axis(s, hi, -1))[..., 0]
    return np.where(n > 0, m, np.nan)


def road_sigma(d_m: np.ndarray) -> float:
    """σ of the road's distances (N,) when defects pull only one way (below, negative).

    MAD over all points counts a pothole filling a third of the overlap as noise (σ 5 mm
    instead of 1 mm, so T_d = 4σ hid a 29 mm pothole). Here the road level is the middle of the
    shortest interval holding half the points (it lies in the road's own distribution while
    defects are a minority), and σ comes from the points above that level only, which no
    defect reaches: 1.4826 · median(d - level | d >= level) (half-normal). NaN when empty.
    """
    v = np.sort(np.asarray(d_m, float)[np.isfinite(d_m)])
    n = v.size
    if n == 0:
        return float("nan")
    if n < 8:
        return robust_sigma(v)
    h = (n + 1) // 2
    i = int(np.argmin(v[h - 1 :] - v[: n - h + 1]))
    level = float(np.median(v[i : i + h]))
    up = v[v >= level] - level
    return float(MAD_TO_SIGMA * np.median(up)) if up.size else robust_sigma(v)


@dataclass
class PlaneFitResult:
    candidate: np.ndarray  # (N,) bool: X^rd, below the road by at least T_d
    dist_m: np.ndarray  # (N,) signed distance to the final plane (m, negative below)
    plane: np.ndarray  # (3,) final plane (p0, p1, p2)
    threshold_m: float  # T_d used (m)
    noise_m: float  # σ of the road points' distances (robust), m
    road_share: float  # T_n = |X^rn| / |X| at the end
    iterations: int


def _start_plane(P: np.ndarray, floor_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Plane and road mask to start the recursion from. A least-squares plane through every
    point tilts toward a large pothole; the road then spreads over ±10 mm and σ (hence T_d)
    swallows the pothole. Refits that drop the points more than the T_d floor below the plane
    (defects only lie below) bring it back onto the road. On a noisy road this trims a little of
    the lower tail; the recursion's own refits over |d| < T_d then restore the plane."""
    plane = fit_plane_z(P)
    road = np.ones(len(P), bool)
    for _ in range(10):
        d = plane_signed_distance(P, plane)
        keep = d > -floor_m
        if keep.sum() < max(3, len(P) // 2) or np.array_equal(keep, road):
            break
        road = keep
        plane = fit_plane_z(P[road])
    return plane, road


def recursive_plane_fit(points_m: np.ndarray, cfg: PlaneFitConfig) -> PlaneFitResult:
    """Split points into road X^rn and candidate defect points X^rd (eq. 4.8-4.10).

    Each round: distances to the current plane; candidates are d_i < 0 and |d_i| >= T_d with
    T_d = max(cfg floor, noise_k · σ) and σ the robust spread of the road points; refit on the
    road points (|d_i| < T_d). Rounds repeat while T_n > m and the split changes. Points more
    than ``max_depth_m`` below the plane are mismatches: neither road nor candidates.
    """
    P = check_shape("points_m", np.asarray(points_m, float), (None, 3))
    n = P.shape[0]
    if n < max(3, cfg.min_points):
        return PlaneFitResult(
            np.zeros(n, bool), np.zeros(n), np.full(3, np.nan), np.nan, np.nan, 1.0, 0
        )
    plane, road = _start_plane(P, cfg.depth_threshold_m)
    cand = np.zeros(n, bool)
    d = plane_signed_distance(P, plane)
    T_d = cfg.depth_threshold_m
    sigma = robust_sigma(d)
    it = 0
    for it in range(1, cfg.max_iterations + 1):
        d = plane_signed_distance(P, plane)
        sigma = road_sigma(d[road])
        T_d = max(cfg.depth_threshold_m, cfg.noise_k * sigma)
        new_cand = (d < 0) & (np.abs(d) >= T_d) & (np.abs(d) <= cfg.max_depth_m)
        # Bumps far above the plane are not road either: keep them out of the refit.
        new_road = (d > -T_d) & (d < T_d)
        share = float(new_road.sum()) / n
        if share <= cfg.min_road_share or new_road.sum() < 3:
            # Too few road points left: the split is no longer a road with defects; keep the
            # previous round's plane and stop (eq. 4.10).
            cand = new_cand
            break
        if np.array_equal(new_cand, cand) and it > 1:
            break
        cand, road = new_cand, new_road
        plane = fit_plane_z(P[road])
    d = plane_signed_distance(P, plane)
    cand = (d < 0) & (np.abs(d) >= T_d) & (np.abs(d) <= cfg.max_depth_m)
    share = 1.0 - float(cand.sum()) / n
    return PlaneFitResult(cand, d, plane, float(T_d), float(sigma), share, it)
