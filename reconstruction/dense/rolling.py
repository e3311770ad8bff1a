"""Rolling shutter in the dense matching: where each frame of a pair saw the road point behind a
pixel of image a's global-shutter grid.

The plane + parallax matching (``parallax``) compares image a and image b resampled onto image
a's ideal pixel grid at the frames' timestamps. With a rolling shutter (camera.yaml
``readout_s``) raw row v was exposed ``readout_s * v / height`` after the timestamp, from a
moved pose, so the plain resampling misplaces the road by the motion during the readout (on a
potholes drive with a 30 ms readout at 6 m/s: flat-road MAE 8.8 mm against 0.95 mm with a
global shutter) and the heights drift across the rows.

Here the road-plane point X of each grid pixel (the pair's plane, camera a at its timestamp) is
projected into each frame with the pose of the row that saw it, under the pair's own
constant-velocity model (``rolling_shutter.poses_at``: frame a's rows at s = τ/Δt, frame b's at
s = 1 + τ/Δt of the motion a -> b). The row depends on the pose and the pose on the row: the
fixed point is ``core.rolling.solve_rows`` (Aitken's acceleration, as for the mosaic). Both images then show the
road where a global shutter at the timestamps would; what is off the plane keeps a residual of
its height times the motion during the readout over the distance.

That residual is not second order: the resampled image a shows the world from the pose of its
row (s_a = τ_a/Δt of the motion a -> b), the resampled image b from s_b = 1 + τ_b/Δt, so an
off-plane point's parallax between them is that of the baseline s_b - s_a, not of the pair's
(s = 0 -> 1) that the plane + parallax model converts it with. Where the road moves across
the rows between the frames (v_b != v_a) the heights come out scaled by s_b - s_a = 1 + k (v_b
- v_a) / height (``baseline_share``; 1.15 on the sample drive at 30 fps with a 20 ms readout:
dense in-pothole MAE 6.7 -> 2.8 mm per pair once divided by it). The parallax is divided by it
before the height is read off (``parallax``). A point's height also lands s_a of its parallax
from its own pixel (up to ~2 px on that drive; left).
"""

from __future__ import annotations

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.rolling import solve_rows
from roadsurf.reconstruction.rolling_shutter import poses_at

TOL_PX = 0.05  # a row still moving by more than this after the solve is not trusted (px)
DENSE_ROLLING_VERSION = 2  # bump when the resampling changes what a pair's heights are


def baseline_share(
    va_raw: np.ndarray, vb_raw: np.ndarray, camera: Camera, frame_dt_s: float
) -> np.ndarray:
    """s_b - s_a (same shape, dimensionless): the share of the pair's motion a -> b between the
    rows va_raw of frame a and vb_raw of frame b (raw px, ``raw_px_from_plane_px``) that saw a
    point: 1 + readout_s (vb - va) / (height frame_dt_s). The resampled pair's parallax is that
    of this baseline (module docstring). NaN stays NaN."""
    k = camera.readout_s / (float(frame_dt_s) * camera.height)
    return 1.0 + k * (np.asarray(vb_raw, float) - np.asarray(va_raw, float))


def raw_px_from_plane_px(
    u: np.ndarray,
    v: np.ndarray,
    camera: Camera,
    R_b_from_a: np.ndarray,
    t_b_from_a_m: np.ndarray,
    plane: np.ndarray,
    frame_dt_s: float,
    frame: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Raw pixels (distorted, as recorded) where frame a (``frame`` 0) or b (1) saw the road-plane
    point behind image a's ideal global-shutter pixels (u, v) (any equal shapes, px).

    R, t: X_b = R X_a + t (m) at the timestamps; plane: (p0, p1, p2), z = p0 x + p1 y + p2 in
    camera a (m); frame_dt_s: b's timestamp minus a's (s). NaN where the ray misses the plane
    (at or above the horizon), where the point is behind the frame's camera, or where the row
    does not settle (``TOL_PX``)."""
    shape = np.shape(u)
    uv1 = np.stack([np.ravel(u), np.ravel(v), np.ones(np.size(u))], axis=1)
    d = uv1 @ np.linalg.inv(camera.K).T
    p0, p1, p2 = (float(x) for x in plane)
    den = d[:, 2] - p0 * d[:, 0] - p1 * d[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(den > 1e-9, p2 / den, np.nan)
    X = d * lam[:, None]  # (N, 3) the plane point in camera a (m); NaN off the plane
    k = camera.readout_s / float(frame_dt_s)

    def project_at_row(v_raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = float(frame) + k * np.nan_to_num(v_raw, nan=0.0) / camera.height
        Rs, ts = poses_at(R_b_from_a, t_b_from_a_m, s)
        Xs = np.einsum("nij,nj->ni", Rs, X) + ts
        return camera.project(Xs)  # NaN behind the camera

    ur, vr = solve_rows(project_at_row, (len(X),))
    _, v_check = project_at_row(vr)
    bad = ~(np.abs(v_check - vr) <= TOL_PX)
    ur, vr = np.where(bad, np.nan, ur), np.where(bad, np.nan, vr)
    return ur.reshape(shape), vr.reshape(shape)
