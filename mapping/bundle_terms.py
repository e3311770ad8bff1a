"""The bundle window's data and its observation terms (issue 30): each track observation's reprojection (u,
v) and point-on-plane (relief) residuals with their derivatives, shared by the whole window's
sparse Jacobian (``mapping.bundle_problem``) and the points' own Gauss-Newton steps
(``mapping.bundle_reduced``, which needs only the dense per-observation point blocks); the focal
scale's effect on the pairs' translations; the k1 correction applied to observed pixels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roadsurf.core.rolling import row_offset


@dataclass
class WindowData:
    """Everything one window's problem needs (frames by their position inside the window)."""

    K: np.ndarray  # (3, 3) intrinsics of the undistorted ideal pixels
    t: np.ndarray  # (F,) frame times (s)
    R0: np.ndarray  # (F, 3, 3) initial world_from_cam rotations
    C0: np.ndarray  # (F, 3) initial camera centres (m)
    free: np.ndarray  # (F,) bool: pose is an unknown (else held)
    C_prior: np.ndarray  # (F, 3) the pose graph's centres (m)
    planes0: np.ndarray  # (F, 3) initial road planes in camera coordinates
    n_up: np.ndarray  # (F, 3) camera-frame axis held vertical by the tilt prior
    obs_f: np.ndarray  # (M,) window frame of each observation
    obs_p: np.ndarray  # (M,) point of each observation
    obs_px: np.ndarray  # (M, 2) ideal pixels
    X0: np.ndarray  # (P, 3) initial points (m)
    gps_t: np.ndarray  # (G,) fix times (s)
    gps_enu: np.ndarray  # (G, 3)
    gps_sigma: np.ndarray  # (G,) horizontal σ (m)
    gps_has_alt: np.ndarray  # (G,) bool
    gap_i: np.ndarray  # (B,) frames i whose motion to i+1 only the prior holds
    obd_i: np.ndarray  # (O,) frames i with a speed for (i, i+1)
    obd_v: np.ndarray  # (O,) m/s
    height_m: float
    sigma_px: float
    sigma_relief_m: float
    sigma_height_m: float
    sigma_prior_m: float
    sigma_tilt_rad: float
    sigma_gap_m: float
    sigma_gap_rad: float
    sigma_obd_mps: float
    vertical_factor: float
    tau0: float  # prior mean of τ (s)
    sigma_tau_s: float  # 0: τ held at tau0
    on_road: np.ndarray | None = None  # (P,) bool: the point-on-plane term applies; None = all
    # the pairs' relative motions (the pose graph's factors): window frames a (K,) and a + 1,
    # R_b_from_a (K, 3, 3) with σ per axis (rad), t_b_from_a (K, 3) with σ per axis (K,) (m)
    rel_i: np.ndarray | None = None
    rel_R: np.ndarray | None = None
    sigma_rel_rad: float = 0.0
    rel_t: np.ndarray | None = None  # None: rotations only
    sigma_rel_m: np.ndarray | None = None
    # (K, 3) unit road normal of each pair in its camera a: with a focal scale the pairs' metric
    # translations (solved with camera.yaml's focal) are rescaled (``pair_translation``)
    rel_n: np.ndarray | None = None
    # focal length: K's fx, fy scaled by exp(ψ); ψ starts at focal0 with a prior σ (0: held)
    focal0: float = 0.0
    sigma_focal: float = 0.0
    # radial distortion: the observed (camera.yaml-undistorted) normalised point is the true one
    # times (1 + κ r²); κ (= true k1 - camera.yaml's k1) starts at k1_0 with a prior σ (0: held)
    k1_0: float = 0.0
    sigma_k1: float = 0.0
    # rolling shutter: each observation's exposure time after its frame's (M,) s and each
    # frame's linear (F, 3) m/s and angular (F, 3) rad/s velocity in the world (held): an
    # observation is projected from its row's pose; None = a global shutter
    obs_time_s: np.ndarray | None = None
    vel: np.ndarray | None = None
    omega: np.ndarray | None = None


def true_px_from_observed_px(px: np.ndarray, K: np.ndarray, kappa: float) -> np.ndarray:
    """(M, 2) ideal pixels of the true camera from (M, 2) pixels undistorted with camera.yaml's
    k1, given the k1 correction κ (−) and K (3, 3): x_obs = x (1 + κ r²) solved for the
    normalised x by fixed-point iteration (|κ r²| ≪ 1)."""
    if kappa == 0.0 or len(px) == 0:
        return px
    f = np.array([K[0, 0], K[1, 1]])
    c = np.array([K[0, 2], K[1, 2]])
    xo = (px - c) / f
    x = xo.copy()
    for _ in range(8):
        x = xo / (1.0 + kappa * np.sum(x**2, axis=1, keepdims=True))
    return x * f + c


def pair_translation(t: np.ndarray, n: np.ndarray, psi: float) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) the pairs' translations t (m, solved with camera.yaml's focal, scaled by the
    camera height) under the focal scale exp(ψ), and their derivative d/dψ (K, 3). A focal
    error maps each pair's scene by A = diag(e^ψ, e^ψ, 1) in its camera (the rays' x/z, y/z
    scale by e^ψ: exact for the points, first order in the inter-frame rotation for the motion)
    and the height scaling then multiplies it by 1 / |A n̂|, n̂ the true road normal; with n the
    pair's own unit normal (K, 3) the true translation is A⁻¹ t |A n|."""
    e = np.exp(psi)
    Ai = np.array([1.0 / e, 1.0 / e, 1.0])
    nxy = n[:, 0] ** 2 + n[:, 1] ** 2
    L = np.sqrt(e * e * nxy + n[:, 2] ** 2)  # |A n|
    g = t * Ai * L[:, None]
    dL = e * e * nxy / L
    dg = t * np.array([-1.0 / e, -1.0 / e, 0.0]) * L[:, None] + t * Ai * dL[:, None]
    return g, dg


def unit_normal(plane: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """(3,) unit normal of a pair's road plane z = p0 x + p1 y + p2 in camera a (``fallback``
    where the plane is not finite)."""
    n = np.array([-plane[0], -plane[1], 1.0]) if np.all(np.isfinite(plane)) else fallback
    return n / np.linalg.norm(n)


@dataclass
class ObsTerms:
    """The M observations' residuals, in σ units, and their derivatives (k: u, v, relief)."""

    res: tuple[np.ndarray, np.ndarray, np.ndarray]  # 3 x (M,) residuals
    A: list[np.ndarray]  # 3 x (M, 3): d res / d(R^T v), rotated to the world
    Ax: list[np.ndarray]  # 3 x (M, 3): d res / d point (world)
    v: np.ndarray  # (M, 3) point minus camera centre (at the row's pose with a rolling shutter)
    u: np.ndarray  # (M,) projected column (px)
    w: np.ndarray  # (M,) projected row (px)
    xn: np.ndarray  # (M,) normalised x
    yn: np.ndarray  # (M,) normalised y
    r2: np.ndarray  # (M,) normalised radius²
    fx: float  # focal lengths with the focal scale (px)
    fy: float
    gpl: np.ndarray  # (M, 3) d relief / d plane (p0, p1, p2)


def observation_terms(
    d: WindowData,
    relief_w: np.ndarray,
    R: np.ndarray,
    C: np.ndarray,
    planes: np.ndarray,
    pts: np.ndarray,
    fs: float,
    kap: float,
) -> ObsTerms:
    """Residuals and derivatives of the observations (d.obs_f, d.obs_p) for the window's (F, 3,
    3) world_from_cam rotations R, (F, 3) centres C, (F, 3) road planes, (P, 3) points (m),
    focal scale fs = exp(ψ) and k1 correction κ; relief_w (M,) the relief term's weight."""
    f, p = d.obs_f, d.obs_p
    m = len(f)
    v = pts[p] - C[f]
    a_rs = None
    if d.obs_time_s is not None and d.vel is not None and d.omega is not None:
        v, a_rs = row_offset(v, d.obs_time_s, d.vel[f], d.omega[f])
    Xc = np.einsum("mji,mj->mi", R[f], v)  # R^T v
    z = np.maximum(Xc[:, 2], 1e-3)
    fx, fy, cx, cy = d.K[0, 0] * fs, d.K[1, 1] * fs, d.K[0, 2], d.K[1, 2]
    xn, yn = Xc[:, 0] / z, Xc[:, 1] / z
    r2 = xn**2 + yn**2
    a = 1.0 + kap * r2  # the k1 correction's radial factor (1 when κ = 0)
    u = fx * xn * a + cx
    w = fy * yn * a + cy
    s = d.sigma_px
    zero = np.zeros(m)
    # d(xn)/dXc = [1/z, 0, -xn/z], d(yn)/dXc = [0, 1/z, -yn/z]
    dxn = np.column_stack([1.0 / z, zero, -xn / z])
    dyn = np.column_stack([zero, 1.0 / z, -yn / z])
    cxy = 2.0 * kap * xn * yn
    Ju = fx * ((a + 2.0 * kap * xn**2)[:, None] * dxn + cxy[:, None] * dyn) / s
    Jv = fy * (cxy[:, None] * dxn + (a + 2.0 * kap * yn**2)[:, None] * dyn) / s
    pl = planes[f]
    # relief as a share of the camera's height above its plane, times h: a metric distance
    # would let the solver shrink the scene to shrink every relief residual (a scale bias only
    # the height prior held back)
    p2 = np.where(np.abs(pl[:, 2]) > 1e-6, pl[:, 2], 1e-6)
    N = pl[:, 0] * Xc[:, 0] + pl[:, 1] * Xc[:, 1] + pl[:, 2] - Xc[:, 2]
    # a defect's point is not held to the road plane (relief_w 0)
    q = d.height_m / (p2 * d.sigma_relief_m) * relief_w
    Jp = np.column_stack([pl[:, 0], pl[:, 1], -np.ones(m)]) * q[:, None]
    A: list[np.ndarray] = []
    Ax: list[np.ndarray] = []
    for Jx in (Ju, Jv, Jp):
        Ak = np.einsum("mi,mji->mj", Jx, R[f])  # d/d(R^T v) rotated to the world
        # v = (I - [a]x)(X - C - vel τ): d/dX = A (I - [a]x) = A + a x A
        A.append(Ak)
        Ax.append(Ak if a_rs is None else Ak + np.cross(a_rs, Ak))
    res = ((u - d.obs_px[:, 0]) / s, (w - d.obs_px[:, 1]) / s, N * q)
    gpl = np.column_stack([Xc[:, 0] * q, Xc[:, 1] * q, q - N * q / p2])
    return ObsTerms(res, A, Ax, v, u, w, xn, yn, r2, fx, fy, gpl)
