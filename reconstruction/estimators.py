"""Two-view estimators on matched, undistorted pixels: the dissertation's method ("proposed"),
its rotation-aware refinement, and the baselines (classic, colmap, stereo).

Every estimator returns a PairResult; failures are statuses with a reason, never exceptions.
All of them share the final steps: epipolar inlier test, triangulation (eq. 3.11-3.12), plane fit
(eq. 3.31), metric scale α = h / d_c (eq. 3.34), signed plane distances and covariances. The
poses come from ``pose_planar`` and ``pose_parallax`` (proposed, rotation_aware) and
``pose_baselines`` (classic, colmap); the stereo rig's pose is its calibration.
"""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np

from roadsurf.core.camera import normalised_from_px, px_from_cam
from roadsurf.core.fits import (
    MAD_TO_SIGMA,
    camera_plane_distance,
    fit_plane_z_trimmed,
    plane_signed_distance,
)
from roadsurf.core.geometry import check_shape
from roadsurf.reconstruction import geometry as g
from roadsurf.reconstruction.config import PriorModel, ReconstructionConfig
from roadsurf.reconstruction.motion_prior import motion_prior_mask
from roadsurf.reconstruction.pose_baselines import pose_classic, pose_colmap
from roadsurf.reconstruction.pose_parallax import (
    parallax_ratio,
    refine_pose_plane_parallax,
    refine_pose_sampson,
)
from roadsurf.reconstruction.pose_planar import (
    estimate_homography,
    pose_plane_from_homography,
    pose_proposed,
    refine_homography_sampson,
)
from roadsurf.reconstruction.types import STATUS_NO_MOTION, PairFailure, PairResult

log = logging.getLogger(__name__)


def estimate_matches(
    px_a: np.ndarray,
    px_b: np.ndarray,
    K: np.ndarray,
    height_m: float,
    cfg: ReconstructionConfig,
    *,
    image_size: tuple[int, int] = (1024, 768),
    road_normal_cam: np.ndarray | None = None,
) -> PairResult:
    """Reconstruct one pair from matched undistorted pixels (N, 2) in a and b.

    height_m is h (camera height above the road, m, perpendicular); image_size = (width,
    height) px; road_normal_cam = (3,) the road's downward normal in camera a's coordinates
    when the mount is known (-``core.geometry.up_in_cam``), None = unknown (the homography
    decomposition then assumes a camera looking down or ahead: ``pose_planar.plane_solutions``).
    Never raises for bad data: the returned PairResult carries status and reason.
    """
    px_a = check_shape("px_a", np.asarray(px_a, dtype=float), (None, 2))
    px_b = check_shape("px_b", np.asarray(px_b, dtype=float), (px_a.shape[0], 2))
    if road_normal_cam is not None:
        road_normal_cam = check_shape("road_normal_cam", np.asarray(road_normal_cam, float), (3,))
        if not np.all(np.isfinite(road_normal_cam)) or np.linalg.norm(road_normal_cam) < 1e-9:
            raise ValueError(
                f"road_normal_cam must be a finite non-zero 3-vector, got {road_normal_cam}"
            )
    res = PairResult(frame_a="", frame_b="", index_a=-1, index_b=-1, method=cfg.method, status="ok")
    res.n_matches = int(px_a.shape[0])
    try:
        _estimate(px_a, px_b, K, height_m, cfg, image_size, res, road_normal_cam)
    except PairFailure as e:
        res.status, res.reason = e.status, e.reason
    except (np.linalg.LinAlgError, cv2.error, ValueError) as e:
        res.status, res.reason = "geometry_failed", f"{type(e).__name__}: {e}"
    return res


def prior_model(cfg: ReconstructionConfig) -> PriorModel:
    """The motion prior's window model for ``cfg.method`` (``prior_model="auto"`` resolved)."""
    if cfg.prior_model != "auto":
        return cfg.prior_model
    return "mean" if cfg.method == "proposed" else "homography"


# the share of a homography's outliers that must fit the epipolar geometry of the pose the
# homography gives for the pair to count as not near-planar (−): points off the road plane
# (kerbs, cars) move along their epipolar lines, so nearly all of them fit; a mismatch does
# so by chance (its residual, beyond the homography's threshold, points anywhere: within
# epi_inlier_px of the line for ~(2/π)·asin(2/ρ), 0.26 at ρ = 5 px, 0.13 at 10 px)
OFF_PLANE_SHARE = 0.5


def _outliers_on_epipolar_lines(
    pa: np.ndarray,
    pb: np.ndarray,
    H: np.ndarray,
    h_inl: np.ndarray,
    K: np.ndarray,
    cfg: ReconstructionConfig,
    road_normal_cam: np.ndarray | None,
) -> float | None:
    """The share (0-1) of the homography's outliers (``~h_inl``) within ``cfg.epi_inlier_px``
    of their epipolar lines under the pose that H's inliers give (pixels (N, 2), K (3, 3)):
    near 1 when the outliers are 3D structure off the plane, low when they are mismatches.
    None when the inliers are too few for a pose."""
    if int(h_inl.sum()) < cfg.min_matches or bool(h_inl.all()):
        return None
    try:
        R, t, _ = pose_plane_from_homography(pa[h_inl], H, K, road_normal_cam=road_normal_cam)
    except PairFailure:
        return None
    F = g.fundamental_from_pose(R, t, K)
    s = np.abs(g.sampson_px(F, pa[~h_inl], pb[~h_inl]))
    return float(np.mean(s < cfg.epi_inlier_px))


# matches below which a failed pose is put down to too little overlap, not to the motion
FEW_MATCHES = 100


def _check_translation_parallax(
    pa: np.ndarray, pb: np.ndarray, R: np.ndarray, K: np.ndarray, min_px: float
) -> None:
    """Raise PairFailure when the camera turned but barely moved: the displacement left after
    removing the rotation (x_b against K R K⁻¹ x_a) is the only depth information, and the
    displacement test before the pose cannot see it (a 10° turn moves every pixel ~100 px)."""
    q = np.column_stack([pa, np.ones(len(pa))]) @ (K @ R @ np.linalg.inv(K)).T
    with np.errstate(divide="ignore", invalid="ignore"):
        par = np.linalg.norm(pb - q[:, :2] / q[:, 2:3], axis=1)
    med = float(np.median(par[np.isfinite(par)])) if np.isfinite(par).any() else 0.0
    if med < min_px:
        turn = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
        # few matches and a large turn: more likely a pose fitted to too little overlap (a
        # dropped frame: 44 matches gave "41°") than a vehicle turning on the spot
        why = (
            f"only {len(pa)} matches fit a pose: the frames may barely overlap (a dropped "
            "frame, a fast stretch), or the camera turned but barely moved"
            if len(pa) < FEW_MATCHES and turn > 10.0
            else f"the camera turned but barely moved ({len(pa)} matches), depth is unobservable"
        )
        raise PairFailure(
            "geometry_failed",
            f"median displacement {med:.2f} px after removing the rotation of {turn:.1f}° "
            f"< {min_px} px: {why}",
        )


def _estimate(
    px_a: np.ndarray,
    px_b: np.ndarray,
    K: np.ndarray,
    height_m: float,
    cfg: ReconstructionConfig,
    image_size: tuple[int, int],
    res: PairResult,
    road_normal_cam: np.ndarray | None,
) -> None:
    t0 = time.perf_counter()
    n = px_a.shape[0]
    idx = np.arange(n)
    if n < cfg.min_matches:
        raise PairFailure("too_few_matches", f"{n} matches < min_matches={cfg.min_matches}")
    method = cfg.method
    keep = np.ones(n, dtype=bool)
    if cfg.motion_prior and method in ("proposed", "rotation_aware"):
        keep = motion_prior_mask(
            px_a, px_b, cfg, model=prior_model(cfg), K=K, road_normal_cam=road_normal_cam
        )
    res.rejected_px_a, res.rejected_px_b = px_a[~keep], px_b[~keep]
    res.n_prior_inliers = int(keep.sum())
    t1 = time.perf_counter()
    res.timings_s["rejection"] = t1 - t0
    if keep.sum() < cfg.min_matches:
        raise PairFailure(
            "too_few_matches",
            f"{int(keep.sum())} matches left after motion-prior rejection (λ={cfg.lambda_prior})",
        )
    pa, pb, idx = px_a[keep], px_b[keep], idx[keep]
    disp = float(np.median(np.linalg.norm(pb - pa, axis=1)))
    if method != "stereo" and disp < cfg.min_displacement_px:
        raise PairFailure(
            STATUS_NO_MOTION,
            f"median displacement {disp:.2f} px < {cfg.min_displacement_px} px: the camera did "
            "not move between the frames (vehicle stopped?), depth is unobservable",
        )

    if method == "stereo":
        # Rectified rig: pose is the calibration (R = I, t = (B, 0, 0)); any vibration of camera 2
        # goes uncorrected, which is what the study measures.
        R, t = np.eye(3), np.array([cfg.stereo_baseline_m, 0.0, 0.0])
        cand = np.ones(len(pa), dtype=bool)
    else:
        if method in ("proposed", "rotation_aware"):
            H, h_inl, out_ratio = estimate_homography(pa, pb, cfg)
            res.H, res.outlier_ratio_h = H, out_ratio
            if out_ratio >= cfg.near_planar_max_outlier:
                fit = _outliers_on_epipolar_lines(pa, pb, H, h_inl, K, cfg, road_normal_cam)
                if fit is None or fit >= OFF_PLANE_SHARE:
                    why = "" if fit is None else f"; {fit:.0%} of them lie off the plane"
                    raise PairFailure(
                        "not_near_planar",
                        f"homography outlier ratio {out_ratio:.2f} >= "
                        f"{cfg.near_planar_max_outlier}{why}",
                    )
                log.debug(
                    "homography outlier ratio %.2f: %.0f%% of the outliers fit the pair's "
                    "epipolar geometry, the rest are mismatches; the pair is near-planar and "
                    "goes on with the homography's inliers",
                    out_ratio,
                    100 * fit,
                )
                # the mismatches that fall near their epipolar lines by chance would be
                # triangulated at wrong depths and outnumber the real parallax points
                pa, pb, idx, h_inl = pa[h_inl], pb[h_inl], idx[h_inl], h_inl[h_inl]
            if h_inl.sum() < cfg.min_matches:
                raise PairFailure("too_few_matches", f"{int(h_inl.sum())} homography inliers")
            if method == "proposed":
                R, t, _ = pose_proposed(
                    pa[h_inl], pb[h_inl], H, K, cfg, road_normal_cam=road_normal_cam
                )
            else:
                H = refine_homography_sampson(pa[h_inl], pb[h_inl], H, K, cfg.ba_iterations)
                res.H = H
                R, t, m = pose_plane_from_homography(
                    pa[h_inl], H, K, road_normal_cam=road_normal_cam
                )
                # Refine on every match consistent with the seed pose (plane + parallax points).
                s = np.abs(g.sampson_px(g.fundamental_from_pose(R, t, K), pa, pb))
                sel = s < max(cfg.epi_inlier_px, cfg.h_ransac_px)
                if sel.sum() >= 8 and cfg.pose_model == "plane_parallax":
                    R, t, kappa = refine_pose_plane_parallax(pa[sel], pb[sel], R, t, m, K)
                    res.config_name = f"kappa={kappa:.3g}"
                elif sel.sum() >= 8:
                    R2, t2 = refine_pose_sampson(pa[sel], pb[sel], R, t, K, cfg.ba_iterations)
                    ratio = parallax_ratio(pa[sel], pb[sel], H, R2, t2, K)
                    res.config_name = f"parallax_ratio={ratio:.2f}"
                    # Model selection: when the plane explains the matches to the noise level,
                    # the homography pose uses the planarity and is the more precise one.
                    if ratio >= cfg.planar_parallax_ratio:
                        R, t = R2, t2
        elif method == "classic":
            R, t, _ = pose_classic(pa, pb, K, cfg)
        elif method == "colmap":
            R, t, name, _ = pose_colmap(pa, pb, K, image_size[0], image_size[1], cfg)
            res.config_name = name
        else:
            raise PairFailure("geometry_failed", f"unknown method {method!r}")
        F = g.fundamental_from_pose(R, t, K)
        res.F = F
        cand = np.abs(g.sampson_px(F, pa, pb)) < cfg.epi_inlier_px
        _check_translation_parallax(pa, pb, R, K, cfg.min_displacement_px)
    t2 = time.perf_counter()
    res.timings_s["geometry"] = t2 - t1

    pa, pb, idx = pa[cand], pb[cand], idx[cand]
    xa, xb = normalised_from_px(pa, K), normalised_from_px(pb, K)
    X = g.triangulate(xa, xb, R, t)
    Xb = X @ R.T + t
    ok = (X[:, 2] > 0) & (Xb[:, 2] > 0)
    err = np.maximum(
        np.linalg.norm(px_from_cam(X, K) - pa, axis=1),
        np.linalg.norm(px_from_cam(Xb, K) - pb, axis=1),
    )
    if method != "stereo":  # the rig's calibrated pose is trusted as is (that is the baseline)
        ok &= err < cfg.max_reproj_px
    if ok.sum() < cfg.min_matches:
        raise PairFailure(
            "geometry_failed", f"only {int(ok.sum())} points triangulate in front of both cameras"
        )
    X, pa, pb, idx = X[ok], pa[ok], pb[ok], idx[ok]
    p, _ = fit_plane_z_trimmed(X, cfg.plane_trim_k)
    d_c = camera_plane_distance(p)
    if not np.isfinite(d_c) or d_c <= 0:
        raise PairFailure("scale_failed", f"camera-to-plane distance d_c={d_c} is not positive")
    alpha = 1.0 if method == "stereo" else height_m / d_c
    Xm = alpha * X
    res.points_cam_a_m = Xm
    res.px_a, res.px_b, res.match_idx = pa, pb, idx.astype(np.int64)
    res.plane = np.array([p[0], p[1], alpha * p[2]])
    res.plane_dist_m = plane_signed_distance(Xm, res.plane)
    sigma = cfg.pixel_sigma_px
    if cfg.estimate_sigma and method != "stereo" and len(pa) >= 8:
        s = g.sampson_px(g.fundamental_from_pose(R, t, K), pa, pb)
        sigma = float(MAD_TO_SIGMA * np.median(np.abs(s))) or sigma
    res.cov_m2 = alpha**2 * g.point_covariance(X, R, t, K, sigma)
    res.R_b_from_a, res.t_b_from_a_m = R, alpha * t
    if method != "stereo" and res.F is not None:
        res.F = g.fundamental_from_pose(R, t, K)
    res.scale_alpha = float(alpha)
    res.n_inliers = int(len(idx))
    res.timings_s["triangulation"] = time.perf_counter() - t2
