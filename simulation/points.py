"""Point-level two-view simulator (dissertation Ch. 3, Table 3.1).

Road points with unevenness δ are seen by camera a (the reference, road plane Z = Z_m in its
frame, camera z down) and by camera b, with X_b = R X_a + t, R from the vibration angles
θx, θy, θz and t = (200, 30, 0) mm by default. Matched pixels get Gaussian noise σ. The camera
height known to the method is ĥ = Z_m − Δh with Δh ~ U(0, δ_h). Seeded and vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roadsurf.core.camera import px_from_cam
from roadsurf.core.geometry import rotation_from_euler_xyz

DEFAULT_F_PX = 960.0  # focal length f (px) of the study camera
DEFAULT_SIZE = (1024, 768)  # image width, height (px)


@dataclass(frozen=True)
class PointScene:
    """Parameters of one simulated pair (lengths in metres, angles in degrees)."""

    delta_m: float = 0.0001  # δ: road unevenness, Z ~ N(Z_m, δ²) (m)
    sigma_px: float = 0.1  # σ: Gaussian pixel noise on every matched coordinate (px)
    z_m: float = 1.1  # Z_m: camera-to-road distance (m)
    theta_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # θx, θy, θz of camera b (deg)
    delta_h_m: float = 0.0  # δ_h: measured height ĥ = Z_m − Δh, Δh ~ U(0, δ_h) (m)
    t_m: tuple[float, float, float] = (0.2, 0.03, 0.0)  # t: translation a -> b (m)
    n_points: int = 200  # matched points per pair (count)
    f_px: float = DEFAULT_F_PX  # focal length (px)
    width: int = DEFAULT_SIZE[0]  # image width (px)
    height: int = DEFAULT_SIZE[1]  # image height (px)


@dataclass
class PointPair:
    """Output of ``simulate_points``. Arrays are (N, 2) px or (N, 3) m in camera a."""

    px_a: np.ndarray  # noisy pixels in a
    px_b: np.ndarray  # noisy pixels in b
    px_a_true: np.ndarray  # noise-free pixels in a
    px_b_true: np.ndarray  # noise-free pixels in b
    X_a_m: np.ndarray  # true 3D points in camera a (m)
    d_true_m: np.ndarray  # (N,) true signed distance to the road plane Z = Z_m (negative below)
    h_measured_m: float  # ĥ, the camera height the method is told (m)
    R_b_from_a: np.ndarray  # (3, 3)
    t_b_from_a_m: np.ndarray  # (3,)
    K: np.ndarray  # (3, 3)
    scene: PointScene


def camera_matrix(scene: PointScene) -> np.ndarray:
    """(3, 3) K of the study camera, fx = fy = ``f_px``, principal point (width/2, height/2).

    Deliberately the pixel-corner convention (origin at the top-left corner of the image, not
    at the centre of its first pixel as ``roadsurf.core.camera.Camera`` and camera.yaml have
    it): points are drawn with u ~ U[0, width), so the study is self-consistent and its
    published numbers stay reproducible. Do not replace it by a ``Camera``'s K."""
    return np.array(
        [
            [scene.f_px, 0.0, scene.width / 2.0],
            [0.0, scene.f_px, scene.height / 2.0],
            [0.0, 0.0, 1.0],
        ]
    )


def simulate_points(scene: PointScene, rng: np.random.Generator | int) -> PointPair:
    """Sample road points visible in both views and return noisy matched pixels + truth."""
    rng = np.random.default_rng(rng)
    K = camera_matrix(scene)
    # R = Rz @ Ry @ Rx of the vibration angles (deg -> rad)
    R = rotation_from_euler_xyz(*np.radians(scene.theta_deg))
    t = np.asarray(scene.t_m, dtype=float)
    Xs: list[np.ndarray] = []
    need = scene.n_points
    for _ in range(50):
        m = 4 * need + 64
        u = rng.uniform(0, scene.width, m)
        v = rng.uniform(0, scene.height, m)
        Z = scene.z_m + rng.normal(0.0, scene.delta_m, m)
        X = np.stack([(u - K[0, 2]) / K[0, 0] * Z, (v - K[1, 2]) / K[1, 1] * Z, Z], axis=1)
        pb = px_from_cam(X @ R.T + t, K)
        inside = (pb[:, 0] >= 0) & (pb[:, 0] < scene.width) & (pb[:, 1] >= 0)
        inside &= pb[:, 1] < scene.height
        Xs.append(X[inside])
        need -= int(inside.sum())
        if need <= 0:
            break
    X = np.concatenate(Xs)[: scene.n_points]
    if X.shape[0] < scene.n_points:
        raise ValueError(
            f"simulate_points: the two views share too little ground for {scene.n_points} points "
            f"(t={scene.t_m} m, Z_m={scene.z_m} m); reduce t or raise Z_m"
        )
    pa_true = px_from_cam(X, K)
    pb_true = px_from_cam(X @ R.T + t, K)
    n = X.shape[0]
    pa = pa_true + rng.normal(0.0, scene.sigma_px, (n, 2))
    pb = pb_true + rng.normal(0.0, scene.sigma_px, (n, 2))
    dh = rng.uniform(0.0, scene.delta_h_m) if scene.delta_h_m > 0 else 0.0
    return PointPair(
        px_a=pa,
        px_b=pb,
        px_a_true=pa_true,
        px_b_true=pb_true,
        X_a_m=X,
        d_true_m=scene.z_m - X[:, 2],
        h_measured_m=scene.z_m - dh,
        R_b_from_a=R,
        t_b_from_a_m=t,
        K=K,
        scene=scene,
    )
