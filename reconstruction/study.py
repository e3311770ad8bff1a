"""Parametric study (dissertation Table 3.1, Figs. 3.6-3.12) on the point-level simulator."""

from __future__ import annotations

import numpy as np

from reconstruction import geometry as g
from reconstruction.types import PairResult
from simulation.points import PointPair


def epsilon(res: PairResult, pp: PointPair) -> float:
    """Eq. 3.36 error (m): ε = (1/N) Σ |ĥ · d̂_i/d̂_c − d_i| over the points the method returned.

    d̂_i/d̂_c is scale-free, so ĥ (the measured height, = Z_m when δ_h = 0) restores metres.
    The stereo baseline is metric by itself, so its d̂_i are compared directly. NaN on failure.
    """
    if not res.ok or res.n_points == 0:
        return float("nan")
    d_true = pp.d_true_m[res.match_idx]
    if res.method == "stereo":
        return float(np.mean(np.abs(res.plane_dist_m - d_true)))
    r = res.plane_dist_m / g.camera_plane_distance(res.plane)
    return float(np.mean(np.abs(pp.h_measured_m * r - d_true)))
