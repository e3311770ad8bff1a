"""Mean shift with a flat kernel (dissertation eq. 5.11-5.12).

Windows of size w x w start on a grid over the map (one per grid cell that holds points), and
each moves to the mean of the points inside it until it stops moving. Windows that converge
together (modes closer than ``merge_m``, w by default) form one cluster, so a defect wider
than w, whose windows stall side by side on its flat bottom, still comes out as one cluster.

Hand-written rather than ``sklearn.cluster.MeanShift``: eq. 5.11's window is a square (a
Chebyshev ball) and the map segmentation weighs each point by its depth, while scikit-learn's
flat kernel is a Euclidean disk without sample weights (measured in docs/detection.md,
"Libraries"; ``make bench-meanshift``).
"""

from __future__ import annotations

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial import cKDTree

from roadsurf.core.geometry import check_shape


def grid_seeds(xy_m: np.ndarray, window_m: float, min_points: int = 1) -> np.ndarray:
    """Start windows (K, 2) m: the centre of mass of the (N, 2) points in each occupied w-cell.

    Cells with fewer than ``min_points`` points start no window; if none is left, one window
    starts at the centre of mass of all points.
    """
    cells = np.floor(xy_m / window_m).astype(np.int64)
    _, inv, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    seeds = np.zeros((counts.size, 2))
    np.add.at(seeds, inv, xy_m)
    seeds /= counts[:, None]
    seeds = seeds[counts >= min_points]
    if seeds.size == 0:
        seeds = xy_m.mean(axis=0, keepdims=True)
    return seeds


def shift_windows(
    xy_m: np.ndarray,
    seeds_m: np.ndarray,
    window_m: float,
    weights: np.ndarray,
    *,
    max_iter: int = 50,
    tol_m: float = 1e-3,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Converged window centres (K, 2) m (eq. 5.12): each w x w window moves to the weighted
    mean of the (N, 2) points inside it until it moves less than ``tol_m`` (per axis)."""
    half = 0.5 * window_m
    tree = cKDTree(xy_m) if tree is None else tree
    modes = seeds_m.copy()
    active = np.ones(len(modes), bool)
    for _ in range(max_iter):
        if not active.any():
            break
        for k in np.flatnonzero(active):
            idx = tree.query_ball_point(modes[k], r=half, p=np.inf)
            if not idx:
                active[k] = False
                continue
            ww = weights[idx]
            new = (xy_m[idx] * ww[:, None]).sum(axis=0) / max(ww.sum(), 1e-12)
            if np.max(np.abs(new - modes[k])) < tol_m:
                active[k] = False
            modes[k] = new
    return modes


def merge_modes(modes_m: np.ndarray, merge_m: float) -> np.ndarray:
    """Group (K,) int in 0..G-1 of each converged window: single linkage, Chebyshev distance,
    cut at ``merge_m`` (windows closer than that, chained, are one cluster)."""
    if len(modes_m) <= 1:
        return np.zeros(len(modes_m), int)
    z = linkage(modes_m, method="single", metric="chebyshev")
    return fcluster(z, merge_m * 1.0001, "distance") - 1


def mean_shift_flat(
    xy_m: np.ndarray,
    window_m: float,
    *,
    weights: np.ndarray | None = None,
    max_iter: int = 50,
    tol_m: float = 1e-3,
    merge_m: float | None = None,
    min_points: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster (N, 2) points with square w x w flat-kernel mean shift.

    Returns (labels (N,) int in 0..K-1, modes (K, 2)). ``weights`` (N,) weigh each point in the
    window mean (e.g. cell depth); ``min_points`` drops seed cells with fewer points.
    """
    xy = check_shape("xy_m", np.asarray(xy_m, float), (None, 2))
    n = xy.shape[0]
    if n == 0:
        return np.zeros(0, int), np.zeros((0, 2))
    if window_m <= 0:
        raise ValueError(f"mean-shift window must be > 0 m, got {window_m}")
    wts = (
        np.ones(n) if weights is None else check_shape("weights", np.asarray(weights, float), (n,))
    )
    tree = cKDTree(xy)
    seeds = grid_seeds(xy, window_m, min_points)
    modes = shift_windows(xy, seeds, window_m, wts, max_iter=max_iter, tol_m=tol_m, tree=tree)
    groups = merge_modes(modes, window_m if merge_m is None else merge_m)
    k = int(groups.max()) + 1
    centres = np.array([modes[groups == g].mean(axis=0) for g in range(k)])
    # Each point belongs to the cluster of its nearest converged window.
    _, nearest = cKDTree(modes).query(xy)
    labels = groups[nearest]
    return labels, centres
