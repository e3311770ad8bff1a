"""Rolling shutter in the two-view geometry (issue 28).

A rolling-shutter sensor exposes its rows one after the other: row v (raw pixel, 0 = top) of a
frame stamped t is seen from the camera's pose at t + τ, τ = readout_s · v / height
(``row_times_s``). With constant velocity over the frame interval Δt (the camera centre moves
on a line, the rotation turns at a constant rate) the camera at fraction s = τ/Δt of the motion
a -> b is X_s = R(s) X + s R(s) Rᵀ t, R(s) = exp(s log R) (``poses_at``; frame b's rows:
s = 1 + τ_b/Δt): the rolling shutter adds no unknowns, every row's pose follows from (R, t).

``estimate_rolling_shutter``:

1. the pair is estimated as a global-shutter pair (``estimate_matches``): mismatch rejection
   and a seed pose, plane and inlier set;
2. ``refine_rolling_shutter``: the plane-plus-parallax maximum likelihood of
   ``pose_parallax.refine_pose_plane_parallax`` with one road homography per match, between
   the poses of its two rows, over the same 8 parameters (R, unit t, plane m);
3. ``shutter_correction``: each match is triangulated from its two rays at their rows' poses
   (a match that does not triangulate plausibly, a mismatch, takes the road plane's point on
   its ray in a) and each observation is moved by the predicted difference between its
   global-shutter and rolling-shutter image, π(K X) − π(K X_s), so the pixel noise stays;
4. the corrected matches are estimated as a global-shutter pair again (any method): the
   geometry at the frames' timestamps. Steps 2-3 repeat from that result; once the
   correction changes by less than ``rs_tol_px`` that estimate is the pair's (typically after
   one or two estimates; a correction still moving after ``rs_iterations`` estimates fails the
   pair, ``geometry_failed``).

Why not just re-estimate from corrected matches until they settle (the first-order
scheme)? That fixed point is unstable: a pose error changes the correction of every row
differently, which the next estimate reads as a larger pose error of the opposite sign (about
−1.4 times as large at 25 m/s, 60 fps, 10 ms readout); step 2 solves for the pose in the
rolling-shutter model itself. The point's own depth (not the plane's) sets its correction, so
the relief keeps its parallax: a plane-only correction would scale a pothole's parallax by
the effective baseline of its two rows, (Δt + τ_b − τ_a) / Δt (~1.3 in that example).
"""

from __future__ import annotations

import logging
import time

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from roadsurf.core.camera import normalised_from_px
from roadsurf.core.geometry import check_shape
from roadsurf.reconstruction import geometry as g
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.estimators import estimate_matches
from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

MAX_REFINE_MATCHES = 1000  # the rolling-shutter pose from at most this many of the inliers,
# evenly spread over their list (its cost grows with them; the final estimate uses all)
MAX_RELIEF_SHARE = 0.5  # a triangulated point farther than this share of the plane's depth
# from the plane is not road (a mismatch): its correction comes from the plane


def row_times_s(v_raw_px: np.ndarray, height_px: int, readout_s: float) -> np.ndarray:
    """(N,) time (s) after the frame's timestamp at which raw pixel rows v were exposed."""
    return readout_s * np.asarray(v_raw_px, float) / float(height_px)


def poses_at(R: np.ndarray, t: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera poses at fractions s (N,) of the motion a -> b under constant velocity:
    (N, 3, 3) R(s) = exp(s log R) and (N, 3) t(s) = s R(s) Rᵀ t, so X_s = R(s) X + t(s) for a
    point X in camera a (s = 0: camera a, s = 1: camera b; any length unit)."""
    return _poses_at_rotvec(Rotation.from_matrix(R).as_rotvec(), R, t, s)


def _poses_at_rotvec(
    w: np.ndarray, R: np.ndarray, t: np.ndarray, s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``poses_at`` with the rotation also given as its rotation vector w = log R."""
    s = np.asarray(s, float)
    Rs = Rotation.from_rotvec(s[:, None] * w[None, :]).as_matrix()
    ts = s[:, None] * np.einsum("nij,j->ni", Rs, R.T @ np.asarray(t, float))
    return Rs, ts


def triangulate_per_ray(
    xa: np.ndarray, xb: np.ndarray, Ra: np.ndarray, ta: np.ndarray, Rb: np.ndarray, tb: np.ndarray
) -> np.ndarray:
    """(N, 3) points from normalised rays xa, xb (N, 2) seen from per-point poses (N, 3, 3),
    (N, 3) (X_cam = R X + t): linear triangulation (``geometry.triangulate`` with a pose per
    ray)."""
    A = np.empty((len(xa), 4, 3))
    b = np.empty((len(xa), 4))
    for k, (x, Rc, tc) in enumerate(((xa, Ra, ta), (xb, Rb, tb))):
        for j in range(2):
            A[:, 2 * k + j] = Rc[:, j] - x[:, j : j + 1] * Rc[:, 2]
            b[:, 2 * k + j] = x[:, j] * tc[:, 2] - tc[:, j]
    AtA = np.einsum("nki,nkj->nij", A, A)
    Atb = np.einsum("nki,nk->ni", A, b)
    return np.linalg.solve(AtA, Atb[..., None])[..., 0]


def _project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.column_stack(
            [K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2], K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]]
        )


def shutter_correction(
    px_a: np.ndarray,
    px_b: np.ndarray,
    s_a: np.ndarray,
    s_b: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    m: np.ndarray,
    K: np.ndarray,
    max_reproj_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2), (N, 2): what to add to the observed pixels px_a, px_b (undistorted) to get the
    global-shutter pixels of cameras a (s = 0) and b (s = 1). s_a, s_b (N,): the rows'
    fractions of the motion (R, t), X_b = R X_a + t; m: the road plane mᵀX = 1 in camera a
    (same length unit as t), for the matches that do not triangulate."""
    Ra, ta = poses_at(R, t, s_a)
    Rb, tb = poses_at(R, t, s_b)
    xa, xb = normalised_from_px(px_a, K), normalised_from_px(px_b, K)
    X = triangulate_per_ray(xa, xb, Ra, ta, Rb, tb)
    Xa_s = np.einsum("nij,nj->ni", Ra, X) + ta
    Xb_s = np.einsum("nij,nj->ni", Rb, X) + tb
    err = np.maximum(
        np.linalg.norm(_project(K, Xa_s) - px_a, axis=1),
        np.linalg.norm(_project(K, Xb_s) - px_b, axis=1),
    )
    # The plane's point on ray a seen from pose s_a: X = λ R_aᵀ x̂ − R_aᵀ t_a with mᵀX = 1.
    ray = np.einsum("nji,nj->ni", Ra, np.column_stack([xa, np.ones(len(xa))]))
    base = np.einsum("nji,nj->ni", Ra, ta)
    with np.errstate(divide="ignore", invalid="ignore"):
        X_plane = ((1.0 + base @ m) / (ray @ m))[:, None] * ray - base
        good = (
            np.all(np.isfinite(X), axis=1)
            & (Xa_s[:, 2] > 0)
            & (Xb_s[:, 2] > 0)
            & (err < max_reproj_px)
            & (np.abs(X[:, 2] / X_plane[:, 2] - 1.0) < MAX_RELIEF_SHARE)
        )
    X = np.where(good[:, None], X, X_plane)
    da = _project(K, X) - _project(K, np.einsum("nij,nj->ni", Ra, X) + ta)
    db = _project(K, X @ R.T + t) - _project(K, np.einsum("nij,nj->ni", Rb, X) + tb)
    bad = ~(np.all(np.isfinite(da), axis=1) & np.all(np.isfinite(db), axis=1))
    da[bad] = 0.0  # behind a camera even on the plane: left as observed (the filters drop it)
    db[bad] = 0.0
    return da, db


def _whitened(
    xa: np.ndarray,
    xb: np.ndarray,
    s_a: np.ndarray,
    s_b: np.ndarray,
    w: np.ndarray,
    t: np.ndarray,
    m: np.ndarray,
    kappa: float,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Whitened plane-plus-parallax residuals (2N,) of homogeneous normalised rays xa (N, 3)
    and xb (N, 2), each match with the road homography between its rows' poses (w: the
    rotation vector of R); the noise model of ``pose_parallax.refine_pose_plane_parallax``:
    covariance σ² (I + J Jᵀ + κ ĝ² ûûᵀ). Also the pieces the κ estimate needs."""
    R = g.rotation_from_axis_angle(w)
    Ra, ta = _poses_at_rotvec(w, R, t, s_a)
    Rb, tb = _poses_at_rotvec(w, R, t, s_b)
    Rrel = Rb @ np.transpose(Ra, (0, 2, 1))
    trel = tb - np.einsum("nij,nj->ni", Rrel, ta)
    # the plane in the pose of row a: mᵀX = 1 with X = R_aᵀ (X_a − t_a)
    m_a = (Ra @ m) / (1.0 + np.einsum("nji,nj->ni", Ra, ta) @ m)[:, None]
    Hn = Rrel + trel[:, :, None] * m_a[:, None, :]
    q = np.einsum("nij,nj->ni", Hn, xa)
    w = q[:, 2]
    xp = q[:, :2] / w[:, None]
    r = xb - xp
    j = (Hn[:, :2, :2] - xp[:, :, None] * Hn[:, 2:3, :2]) / w[:, None, None]  # ∂π(Hx)/∂(u, v)
    c11 = 1 + j[:, 0, 0] ** 2 + j[:, 0, 1] ** 2
    c12 = j[:, 0, 0] * j[:, 1, 0] + j[:, 0, 1] * j[:, 1, 1]
    c22 = 1 + j[:, 1, 0] ** 2 + j[:, 1, 1] ** 2
    u = trel[:, :2] - trel[:, 2:3] * xp  # towards the epipole: the parallax direction
    gl = np.linalg.norm(u, axis=1) + 1e-300
    u = u / gl[:, None]
    g2 = gl**2 / np.mean(gl**2)
    s11 = c11 + kappa * g2 * u[:, 0] ** 2
    s12 = c12 + kappa * g2 * u[:, 0] * u[:, 1]
    s22 = c22 + kappa * g2 * u[:, 1] ** 2
    l11 = np.sqrt(s11)
    l21 = s12 / l11
    l22 = np.sqrt(np.maximum(s22 - l21**2, 1e-300))
    rw1 = r[:, 0] / l11
    rw2 = (r[:, 1] - l21 * rw1) / l22
    return np.concatenate([rw1, rw2]), dict(r=r, u=u, g2=g2, c11=c11, c12=c12, c22=c22)


def _kappa(st: dict[str, np.ndarray], kappa_z: float = 2.0) -> float:
    """Relief variance κ by the method of moments (as ``refine_pose_plane_parallax``)."""
    u, r = st["u"], st["r"]
    c11, c12, c22 = st["c11"], st["c12"], st["c22"]
    par = r[:, 0] * u[:, 0] + r[:, 1] * u[:, 1]
    perp = -r[:, 0] * u[:, 1] + r[:, 1] * u[:, 0]
    c_par = c11 * u[:, 0] ** 2 + 2 * c12 * u[:, 0] * u[:, 1] + c22 * u[:, 1] ** 2
    c_perp = c11 * u[:, 1] ** 2 - 2 * c12 * u[:, 0] * u[:, 1] + c22 * u[:, 0] ** 2
    sigma2 = float(np.mean(perp**2) / np.mean(c_perp)) + 1e-300
    k_i = (par**2 / sigma2 - c_par) / np.mean(st["g2"])
    k_se = float(np.std(k_i) / np.sqrt(len(k_i)))
    return float(np.clip(np.mean(k_i) - kappa_z * k_se, 0.0, 1e8))


def refine_rolling_shutter(
    px_a: np.ndarray,
    px_b: np.ndarray,
    s_a: np.ndarray,
    s_b: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    m0: np.ndarray,
    K: np.ndarray,
    *,
    outer: int = 2,
    max_nfev: int = 400,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Plane-plus-parallax maximum likelihood of (R, unit t, m) for rolling-shutter matches
    (undistorted pixels (N, 2); s_a, s_b their rows' fractions of the motion), from a seed with
    K⁻¹HK ∝ R + t mᵀ: first the plane model alone (κ = 0), then ``outer`` times κ estimated
    and the fit redone. Levenberg–Marquardt with forward-difference Jacobians (``max_nfev``
    residual evaluations each). Returns (R, t, m, κ)."""
    xa = np.column_stack([normalised_from_px(px_a, K), np.ones(len(px_a))])
    xb = normalised_from_px(px_b, K)
    t0 = t0 / np.linalg.norm(t0)
    a = np.array([1.0, 0, 0]) if abs(t0[0]) < 0.9 else np.array([0, 1.0, 0])
    b1 = np.cross(t0, a)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(t0, b1)

    w0 = Rotation.from_matrix(R0).as_rotvec()

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rotation vector of R, unit t, m); the rotation vector moves additively (no
        matrix logarithm per evaluation)."""
        t = t0 + p[3] * b1 + p[4] * b2
        return w0 + p[:3], t / np.linalg.norm(t), m0 + p[5:8]

    p = np.zeros(8)
    kappa = 0.0
    for it in range(max(1, outer) + 1):
        # The seed's pose is off by the rolling shutter's share: the plane model alone (κ = 0)
        # first, as with a large κ the plane is barely constrained and the fit crawls.
        if it > 0:
            kappa = _kappa(_whitened(xa, xb, s_a, s_b, *unpack(p), 0.0)[1])
        sol = least_squares(
            lambda q, k=kappa: _whitened(xa, xb, s_a, s_b, *unpack(q), k)[0],
            p,
            method="lm",
            x_scale="jac",
            max_nfev=max_nfev,
        )
        p = sol.x
    w, t, m = unpack(p)
    return g.rotation_from_axis_angle(w), t, m, kappa


def _plane_m(res: PairResult) -> np.ndarray:
    """The road plane of a result as mᵀX = 1 in camera a, in units of its |t| (1/|t| m)."""
    p0, p1, p2 = res.plane
    return np.array([-p0, -p1, 1.0]) / p2 * float(np.linalg.norm(res.t_b_from_a_m))


def estimate_rolling_shutter(
    px_a: np.ndarray,
    px_b: np.ndarray,
    K: np.ndarray,
    height_m: float,
    cfg: ReconstructionConfig,
    *,
    tau_a_s: np.ndarray,
    tau_b_s: np.ndarray,
    frame_dt_s: float,
    image_size: tuple[int, int] = (1024, 768),
    road_normal_cam: np.ndarray | None = None,
) -> PairResult:
    """``estimate_matches`` for a rolling-shutter camera (module docstring). tau_a_s, tau_b_s
    (N,): each observation's exposure time after its frame's timestamp (``row_times_s``);
    frame_dt_s: timestamp of b minus that of a (s, > 0).

    The result is the geometry at the frames' timestamps: R, t, the plane and the points in
    camera a at its timestamp (row 0), covariances of the corrected observations.
    ``px_a``/``px_b``/``rejected_px_*`` stay the observed (undistorted) pixels: the image
    content is there. ``config_name`` gets ``rs_iterations=k`` appended (k estimates from
    corrected matches), ``timings_s["rolling_shutter"]`` the time of steps 2-3.
    """
    px_a = check_shape("px_a", np.asarray(px_a, float), (None, 2))
    px_b = check_shape("px_b", np.asarray(px_b, float), (px_a.shape[0], 2))
    tau_a = check_shape("tau_a_s", np.asarray(tau_a_s, float), (px_a.shape[0],))
    tau_b = check_shape("tau_b_s", np.asarray(tau_b_s, float), (px_a.shape[0],))
    if not (np.isfinite(frame_dt_s) and frame_dt_s > 0):
        raise ValueError(f"frame_dt_s must be a positive number of seconds, got {frame_dt_s!r}")
    s_a, s_b = tau_a / frame_dt_s, 1.0 + tau_b / frame_dt_s

    def estimate(pa: np.ndarray, pb: np.ndarray) -> PairResult:
        return estimate_matches(
            pa, pb, K, height_m, cfg, image_size=image_size, road_normal_cam=road_normal_cam
        )

    res = estimate(px_a, px_b)
    if not res.ok:
        res.reason += " (before the rolling-shutter correction)"
        return res
    t_rs = 0.0
    da, db = np.zeros_like(px_a), np.zeros_like(px_b)
    rounds = 0  # estimates from corrected matches
    while True:
        t0 = time.perf_counter()
        sel = res.match_idx
        if len(sel) > MAX_REFINE_MATCHES:
            sel = sel[np.linspace(0, len(sel) - 1, MAX_REFINE_MATCHES).astype(int)]
        t_unit = res.t_b_from_a_m / np.linalg.norm(res.t_b_from_a_m)
        try:
            R, t, m, _ = refine_rolling_shutter(
                px_a[sel], px_b[sel], s_a[sel], s_b[sel], res.R_b_from_a, t_unit, _plane_m(res), K
            )
            da_new, db_new = shutter_correction(px_a, px_b, s_a, s_b, R, t, m, K, cfg.max_reproj_px)
        except (np.linalg.LinAlgError, ValueError) as e:  # a degenerate seed or NaNs
            failed = PairResult("", "", -1, -1, cfg.method, "geometry_failed")
            failed.reason = f"rolling-shutter correction failed ({type(e).__name__}: {e})"
            failed.n_matches = res.n_matches
            return failed
        t_rs += time.perf_counter() - t0
        change = float(np.max(np.abs(np.concatenate([da_new - da, db_new - db]))))
        if rounds > 0 and change < cfg.rs_tol_px:
            break  # the current estimate's correction is this one (to within rs_tol_px)
        if rounds == cfg.rs_iterations:
            failed = PairResult("", "", -1, -1, cfg.method, "geometry_failed")
            failed.reason = (
                f"rolling-shutter correction did not settle: it still moved a match by "
                f"{change:.2g} px after {rounds} rounds (rs_iterations; rs_tol_px = "
                f"{cfg.rs_tol_px:g})"
            )
            failed.n_matches = res.n_matches
            return failed
        da, db = da_new, db_new
        res = estimate(px_a + da, px_b + db)
        rounds += 1
        if not res.ok:
            res.reason += f" (after the rolling-shutter correction, round {rounds})"
            return res
    idx = res.match_idx
    res.px_a, res.px_b = px_a[idx], px_b[idx]
    res.rejected_px_a, res.rejected_px_b = _observed_rejected(res, px_a + da, px_a, px_b)
    res.config_name = ";".join(x for x in (res.config_name, f"rs_iterations={rounds}") if x)
    res.timings_s["rolling_shutter"] = t_rs
    return res


def _observed_rejected(
    res: PairResult, corrected_a: np.ndarray, px_a: np.ndarray, px_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The observed pixels of the matches the motion prior rejected (the estimator records
    the corrected ones, rows of ``corrected_a``)."""
    rej = np.asarray(res.rejected_px_a, float).reshape(-1, 2)
    if len(rej) == 0:
        return rej, rej.copy()
    where: dict[tuple[float, float], list[int]] = {}
    for i, p in enumerate(map(tuple, corrected_a)):
        where.setdefault(p, []).append(i)
    idx = [where[p].pop(0) for p in map(tuple, rej)]
    return px_a[idx], px_b[idx]
