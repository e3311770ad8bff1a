"""Rolling shutter in the world: where a world point appears in a frame whose rows were exposed
one after another while the vehicle moved (issue 28).

Convention (``Camera.readout_s``, docs/formats.md): raw row v (pixel centres, 0 = top) is exposed
``readout_s * v / height`` seconds after the frame's timestamp, so the frame's pose
(``Trajectory.world_from_cam``) is its first row's. At 100 km/h a 20 ms readout moves the camera
0.55 m between the first and the last row: a map cell projected with the frame's pose alone lands
tens of pixels from where the image saw it.

The motion over one readout is taken as constant: a linear velocity (m/s) and an angular velocity
(rad/s), both in the world (ENU) frame, estimated from the neighbouring frames' poses
(``frame_motion``). The row of a point depends on the pose, which depends on the row: the fixed
point is found with Aitken's acceleration of the plain iteration, which is exact when the row is
linear in the exposure time (the iteration contracts by the ratio of the motion during readout to
the footprint, about 0.4 at 100 km/h with 20 ms).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.core.camera import Camera


def frame_motion(
    world_from_cam: np.ndarray,
    timestamp_s: np.ndarray,
    i: int,
    segment: np.ndarray | None = None,
    max_gap_s: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Linear (3,) m/s and angular (3,) rad/s velocity of frame ``i`` in the world frame, from
    its neighbours (central difference where both exist in the same ``segment`` within
    ``max_gap_s``, else one-sided; zero when it has none).

    ``world_from_cam``: (N, 4, 4) camera-to-world poses (m); ``timestamp_s``: (N,) s."""
    n = len(world_from_cam)
    t = np.asarray(timestamp_s, float)

    def usable(j: int) -> bool:
        if not 0 <= j < n or j == i or not np.isfinite(world_from_cam[j]).all():
            return False
        if segment is not None and segment[j] != segment[i]:
            return False
        return 0 < abs(t[j] - t[i]) <= max_gap_s

    nb = [j for j in (i - 1, i + 1) if usable(j)]
    if not nb or not np.isfinite(world_from_cam[i]).all():
        return np.zeros(3), np.zeros(3)
    a, b = (nb[0], nb[-1]) if len(nb) == 2 else (min(i, nb[0]), max(i, nb[0]))
    dt = t[b] - t[a]
    Ta, Tb = world_from_cam[a], world_from_cam[b]
    vel = (Tb[:3, 3] - Ta[:3, 3]) / dt
    dR = Tb[:3, :3] @ Ta[:3, :3].T  # world rotation from a to b
    return vel, Rotation.from_matrix(dR).as_rotvec() / dt


def row_offset(
    v: np.ndarray, tau_s: np.ndarray, vel: np.ndarray, omega: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A rolling shutter's row pose: the camera at τ after the frame's time has moved by vel τ
    and turned by a = ω τ (small angle, world frame), so a point seen from it is
    Rᵀ (I - [a]x)(X - C - vel τ) with the frame's R, C. v: (..., 3) world vectors X - C (m);
    tau_s (...,) s; vel, omega (..., 3) m/s, rad/s (constant over the readout,
    ``frame_motion``). Returns (I - [a]x)(v - vel τ) (..., 3) and a."""
    a = omega * tau_s[..., None]
    w = v - vel * tau_s[..., None]
    return w - np.cross(a, w), a


def raw_px_from_world(
    camera: Camera,
    X_world: np.ndarray,
    world_from_cam: np.ndarray,
    velocity: np.ndarray | None = None,
    omega: np.ndarray | None = None,
    rounds: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Raw (distorted) pixel u, v (...) of world points (..., 3) (m) in a frame with pose
    ``world_from_cam`` (4, 4) at its first row, moving with ``velocity`` (3,) m/s and ``omega``
    (3,) rad/s (world frame) during the camera's readout. A global shutter (``readout_s`` 0) or no
    motion is the plain projection. NaN where the point is behind the camera."""
    X = np.asarray(X_world, float)
    R, C = world_from_cam[:3, :3], world_from_cam[:3, 3]
    if camera.readout_s <= 0 or velocity is None:
        return camera.project((X - C) @ R)
    vel = np.asarray(velocity, float)
    om = np.zeros(3) if omega is None else np.asarray(omega, float)
    k = camera.readout_s / camera.height  # s per row

    def row_after(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, _ = row_offset(X - C, np.nan_to_num(v, nan=0.0) * k, vel, om)
        return camera.project(d @ R)

    return solve_rows(row_after, X.shape[:-1], rounds)


def solve_rows(
    project_at_row: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    shape: tuple[int, ...],
    rounds: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """The raw pixels (u, v) of points in a rolling-shutter frame: the fixed point v =
    project_at_row(v)[1], where ``project_at_row(v)`` projects each point with the pose of raw
    row v (any shape ``shape``, px). Aitken's acceleration of the plain iteration, ``rounds``
    times (exact when the row is linear in the exposure time; the plain iteration contracts by
    the image's own motion during the readout over the image height). NaN stays NaN."""
    u, v = project_at_row(np.zeros(shape))
    for _ in range(rounds):
        v0 = v
        _, v1 = project_at_row(v0)
        _, v2 = project_at_row(v1)
        den = v2 - 2.0 * v1 + v0
        with np.errstate(divide="ignore", invalid="ignore"):
            acc = v0 - (v1 - v0) ** 2 / den
        v = np.where(np.abs(den) > 1e-9, acc, v2)
    return project_at_row(v)
