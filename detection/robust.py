"""The maximum depth of a defect as a robust statistic with a minimum support.

A defect's reported ``max_depth_m`` sets its severity, so one wrong observation must not set
it: a mismatched feature, a failed dense track or a raster cell filled from one such point can
read decimetres deep (a fault campaign saw a pothole 18.6 mm deep reported at 107.7 mm).

``supported_max`` is the deepest value that at least ``k`` observations reach: the deepest
value ``v`` with ``k - 1`` others no shallower than ``v - tol``, where ``tol`` = max(``tol_m``,
``tol_frac`` x the shallower value). Sorted deepest first, that is the first ``v[i]`` with
``v[i] - v[i + k - 1] <= tol``; when no value has that support it is the ``k``-th deepest
value (an order statistic, which ``k - 1`` outliers cannot move either).

Why this and not a percentile or the mean of the deepest ``k``: a pothole's bottom is a small
share of its outline (a P95 of a bowl reads it several millimetres shallow), and an outlier
10 cm deep moves the mean of the deepest ``k`` by 10 cm / ``k``. The supported maximum keeps
the true deepest value whenever ``k`` observations of the bottom agree within the tolerance
(the bottom of a bowl is flat to a millimetre over its deepest few centimetres), and needs
``k`` outliers that also agree with each other to be moved. The tolerance (5 mm or 20 %) is the
rule the map points used before for one isolated deepest point.

Minimum supports, by observation (module constants, not settings: they define the statistic):

- sparse 3D points (map points, each pair's own points): ``POINT_SUPPORT`` = 2 independent
  points; the pairs' readings are then combined by their median, so a mismatch must recur;
- raster cells of the map's surface (5 mm GSD): ``CELL_SUPPORT`` = 4 cells (1 cm²), since
  one mapped outlier point spreads into the cells around it;
- dense depth cells (after their 3 x 3 median): ``DENSE_SUPPORT`` = 3 cells; before that,
  a pair's cell reading the other pairs that saw the cell do not support is dropped
  (``dense._drop_unsupported``: a band of failed tracks in one of two pairs).

When the fused map's points read a defect deeper than every pair that measured it in its own
frame, the map's reading must be supported by the pairs' (``supported_by``, the same
tolerance): the map's points ARE the pairs' points, placed by the trajectory, so a depth the
pairs themselves do not see comes from the placement (a pose error, two stretches of road fused
into one place), not from the road. Likewise a dense-track reading deeper than the fused dense
surface supports (``measurement``): the two are matchers of the same images, and tracks that
failed over a pothole floor read it deep together (a supported maximum cannot catch a whole
floor of them).

Cracks keep the median over their pieces of each piece's second-deepest point (at least two
points per piece); ruts the largest running median of the stations' depths.
"""

from __future__ import annotations

import numpy as np

POINT_SUPPORT = 2  # sparse 3D points that must reach the max depth (count)
CELL_SUPPORT = 4  # raster cells of the surface map that must reach it (count; 1 cm² at 5 mm)
DENSE_SUPPORT = 3  # dense depth cells (3 x 3 median-filtered) that must reach it (count)
SUPPORT_TOL_M = 0.005  # observations within max(this, frac x depth) support a depth (m)
SUPPORT_TOL_FRAC = 0.2  # ... relative part of that tolerance (0-1)


def supported_max(
    values: np.ndarray,
    k: int,
    tol_m: float = SUPPORT_TOL_M,
    tol_frac: float = SUPPORT_TOL_FRAC,
) -> float | None:
    """Deepest value of ``values`` (N,) reached by at least ``k`` of them (see module doc).

    NaN values are ignored. With fewer than ``k`` finite values: the smallest of them (no value
    has the support, the shallowest is the one the others cannot have pushed up); None when
    there is none.
    """
    v = np.asarray(values, float).ravel()
    v = np.sort(v[np.isfinite(v)])[::-1]
    if len(v) == 0:
        return None
    k = max(1, int(k))
    if len(v) < k:
        return float(v[-1])
    lo = v[k - 1 :]
    hi = v[: len(lo)]
    ok = hi - lo <= np.maximum(tol_m, tol_frac * np.abs(lo))
    return float(hi[np.argmax(ok)]) if ok.any() else float(v[k - 1])


def supported_by(value: float, reference: float) -> bool:
    """Whether a depth ``value`` (m) is supported by an independent ``reference`` reading: no
    deeper than it by more than max(``SUPPORT_TOL_M``, ``SUPPORT_TOL_FRAC`` x reference)."""
    return value - reference <= max(SUPPORT_TOL_M, SUPPORT_TOL_FRAC * abs(reference))
