"""How much a pair's geometry can say about a crack's depth: the parallax across the crack.

A point ``D`` below the road moves between the two images by ``J D`` (J: image motion per metre
of depth at that pixel, from the pair's R, t, K and road plane). On a line, matching (LK,
the groove model, a sparse feature's window) sees only the motion across it (the aperture
problem): a crack depth D shows as ``|c·J| D`` pixels, c the crack's normal in image b. Under a
camera moving forward the parallax runs along the direction of travel on the road (every
epipolar plane holds the baseline, which lies in the road), so a crack running with the travel
has almost no depth signal, however deep it is; what the pair's points and dense tracks read on
it is their slide along the line (docs/detection.md, *Cracks along the direction of travel*).

``across_parallax`` gives, per crack piece, the share |c·J| / |J| (sine of the angle between
the crack and the epipolar direction) and |c·J| in pixels per metre, medians over the centre
line, for ``crackmap`` to decide where the 3D test is informative.
"""

from __future__ import annotations

import numpy as np

from roadsurf.detection.crackdepth import PairView, project_px, ray_points, tangents


def across_parallax(
    line_px_raw: np.ndarray, view: PairView, plane: np.ndarray, radius_px: float = 3.5
) -> tuple[float, float]:
    """(share, px_per_m) of one crack piece: medians over its centre-line pixels of
    |c·J| / |J| (0: the crack runs with the parallax, 1: across it) and of |c·J| (pixels of
    motion across the crack per metre of depth below the road).

    line_px_raw: (N, 2) raw pixels of the centre line in image a; ``plane``: the pair's road
    plane in camera a, Z = p0 X + p1 Y + p2 (m). (nan, nan) for fewer than 3 pixels or a line
    not in front of the camera.
    """
    raw = np.asarray(line_px_raw, float).reshape(-1, 2)
    if len(raw) < 3:
        return float("nan"), float("nan")
    cam = view.camera
    K = cam.K
    pa = cam.undistort_px(raw)
    X0 = ray_points(pa, K, plane, 0.0)
    if not np.all(X0[:, 2] > 0):
        return float("nan"), float("nan")
    p0 = project_px(X0, view)
    J = (project_px(ray_points(pa, K, plane, 1e-3), view) - p0) / 1e-3  # px per m of depth
    tan_a = tangents(pa, radius_px)
    ends = [project_px(ray_points(pa + d * tan_a, K, plane, 0.0), view) for d in (-1, 1)]
    tan_b = ends[1] - ends[0]
    tan_b /= np.maximum(np.linalg.norm(tan_b, axis=1, keepdims=True), 1e-12)
    nrm_b = np.c_[-tan_b[:, 1], tan_b[:, 0]]
    cj = np.abs(np.sum(nrm_b * J, axis=1))
    nj = np.linalg.norm(J, axis=1)
    share = cj / np.maximum(nj, 1e-12)
    return float(np.median(share)), float(np.median(cj))
