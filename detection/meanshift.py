"""Mean shift with a flat kernel (dissertation eq. 5.11-5.12).

Windows of size w x w start on a grid over the map (one per grid cell that holds points), and
each moves to the mean of the points inside it until it stops moving. Windows that converge
together (modes closer than ``merge_m``, w by default) form one cluster, so a defect wider
than w, whose windows stall side by side on its flat bottom, still comes out as one cluster.
"""

from __future__ import annotations

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial import cKDTree

from roadsurf.core.geometry import check_shape


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
    half = 0.5 * window_m
    tree = cKDTree(xy)
    # Seeds: the centre of mass of the points in each occupied grid cell of size w.
    cells = np.floor(xy / window_m).astype(np.int64)
    _, inv, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    seeds = np.zeros((counts.size, 2))
    np.add.at(seeds, inv, xy)
    seeds /= counts[:, None]
    seeds = seeds[counts >= min_points]
    if seeds.size == 0:
        seeds = xy.mean(axis=0, keepdims=True)
    modes = seeds.copy()
    active = np.ones(len(modes), bool)
    for _ in range(max_iter):
        if not active.any():
            break
        for k in np.flatnonzero(active):
            idx = tree.query_ball_point(modes[k], r=half, p=np.inf)
            if not idx:
                active[k] = False
                continue
            ww = wts[idx]
            new = (xy[idx] * ww[:, None]).sum(axis=0) / max(ww.sum(), 1e-12)
            if np.max(np.abs(new - modes[k])) < tol_m:
                active[k] = False
            modes[k] = new
    # Windows that converged together (within merge_m, chained) are one cluster.
    merge = window_m if merge_m is None else merge_m
    if len(modes) > 1:
        groups = (
            fcluster(
                linkage(modes, method="single", metric="chebyshev"), merge * 1.0001, "distance"
            )
            - 1
        )
    else:
        groups = np.zeros(1, int)
    k = int(groups.max()) + 1
    centres = np.array([modes[groups == g].mean(axis=0) for g in range(k)])
    # Each point belongs to the cluster of its nearest converged window.
    _, nearest = cKDTree(modes).query(xy)
    labels = groups[nearest]
    return labels, centres
