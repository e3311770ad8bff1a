"""Configuration of the reconstruction stage (dissertation Ch. 3-4). Frozen dataclasses.

Symbols follow the dissertation: λ (motion-prior width, eq. 4.7), σ (pixel noise, eq. 3.27),
h (camera height, eq. 3.34), α = h / d_c (metric scale).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

FeatureKind = Literal["sift", "orb", "akaze"]
Method = Literal["proposed", "rotation_aware", "classic", "colmap", "stereo"]
METHODS: tuple[str, ...] = ("proposed", "rotation_aware", "classic", "colmap", "stereo")
PriorModel = Literal["mean", "affine", "homography"]


@dataclass(frozen=True)
class FeatureConfig:
    """Feature detection and matching."""

    kind: FeatureKind = "sift"  # detector/descriptor: sift (default) | orb | akaze
    max_features: int = 2500  # cap on keypoints per frame (count); bounds the matching time
    ratio: float = 0.8  # Lowe ratio test, best/second-best descriptor distance (unitless)
    matcher: Literal["flann", "bf"] = "flann"  # float descriptors: FLANN kd-trees (fast) or brute
    # force (exact); binary descriptors (ORB/AKAZE) always use brute-force Hamming
    flann_checks: int = 32  # FLANN leaf checks per query (count): more = closer to exact
    mutual: bool = True  # keep only mutual nearest neighbours (a->b and b->a agree)
    grid_cells: int = 12  # spread keypoints over a grid_cells x grid_cells grid (count); 0 = off.
    # Even coverage raised the sample drive's map coverage from 79% (off) to 89% (8x8) and 92%
    # (12x12 or 16x16, uncapped candidates); 16x16 cost 0.3 mm in-pothole pair RMSE
    contrast_threshold: float = 0.01  # SIFT DoG contrast threshold (unitless, OpenCV default
    # 0.04). Low, because the grid quota keeps the strongest keypoints of each cell: in effect
    # a lower threshold only in weak cells (shadows, dark pothole floors). Sample drive:
    # coverage 91.4 -> 92.1%, in-defect height MAE 5.8 -> 4.0 mm vs 0.04
    n_octave_layers: int = 3  # SIFT scales per octave (count, OpenCV default 3)
    candidates_per_feature: float = 0.0  # detector cap = this x max_features before the grid
    # spread (unitless); 0 = no cap, so weak cells keep their candidates (only the kept
    # keypoints are described, so candidates are cheap)
    clahe_clip: float = 0.0  # CLAHE clip limit on the grey image before detection (unitless;
    # 0 = off); for detection/description only, the images themselves are untouched
    clahe_tiles: int = 8  # CLAHE tiles per image side (count)
    border_pad_px: int = 0  # mirror-pad the detection image by this (px at detection scale) so
    # SIFT also finds keypoints at the image edges (the corridor's sides); keypoints in the
    # padding are dropped
    downscale: float = 1.0  # detect on an image resized by this factor (unitless, <= 1)
    max_detect_megapixels: float = 0.3  # ... and at most this many Mpx (0 = off): SIFT's cost
    # grows with the area; 1024x768 -> 0.62x (same flat-road RMSE as 0.45 Mpx on the speed
    # drive, ~30% less detection CPU), 640x480 untouched (scales >= 0.95 are not applied)
    stretch_retry: tuple[float, ...] = (0.7071, 0.5)  # vertical scales of image b (unitless,
    # (0, 1]) at which its features are detected again when a pair fails for want of matches
    # (ASIFT's tilt simulation along the image's vertical, in ASIFT's sqrt(2) steps): a forward-
    # tilted camera sees a road patch less foreshortened in b (nearer) than in a, and a top-down
    # rolling-shutter readout while the road moves down the image stretches it further, beyond
    # what SIFT's descriptors tolerate (40° mount, 94 km/h, 20 ms readout: 0/7 pairs ok, 6/7
    # with 0.7071 or 0.5). () = off; failed pairs only, so a good drive pays nothing

    # valid values (interval notation; see roadsurf.core.config)
    RANGES: ClassVar[dict[str, str]] = {
        "max_features": "[1, inf)",
        "ratio": "(0, 1]; best/second-best distance",
        "flann_checks": "[1, inf)",
        "grid_cells": "[0, inf); 0 = off",
        "contrast_threshold": "[0, 1]",
        "n_octave_layers": "[1, inf)",
        "candidates_per_feature": "[0, inf); 0 = no cap",
        "clahe_clip": "[0, inf); 0 = off",
        "clahe_tiles": "[1, inf)",
        "border_pad_px": "[0, inf)",
        "downscale": "(0, 1]; detection never upsamples",
        "max_detect_megapixels": "[0, inf); 0 = off",
        "stretch_retry": "(0, 1]; each a vertical scale of image b",
    }


@dataclass(frozen=True)
class ProbeConfig:
    """The cheap two-view probe (``reconstruction.probe``): Shi-Tomasi corners of frame a tracked
    into b by pyramidal Lucas-Kanade from a coarse SIFT homography, then the same estimator chain
    as a full pair. The fused run's 3D audit uses it to find out whether a stretch of road has
    any depth before paying for a full pair (about 60 ms against 450 ms of CPU at 640x480)."""

    coarse_megapixels: float = 0.04  # the coarse SIFT alignment runs on frames resized to this
    # (Mpx); it only seeds the tracker, whose pyramid absorbs its error
    coarse_features: int = 400  # SIFT keypoints per frame at the coarse scale (count)
    corners: int = 800  # Shi-Tomasi corners tracked from frame a (count)
    corner_quality: float = 0.001  # corner strength relative to the strongest one (0-1)
    corner_spacing_px: float = 10.0  # minimum distance between corners (px)
    window_px: int = 21  # Lucas-Kanade window side (px)
    pyramid_levels: int = 2  # Lucas-Kanade pyramid levels above full resolution (count)
    max_fb_error_px: float = 0.3  # drop a track whose forward-backward error exceeds this (px)

    RANGES: ClassVar[dict[str, str]] = {
        "coarse_megapixels": "(0, inf)",
        "coarse_features": "[1, inf)",
        "corners": "[1, inf)",
        "corner_quality": "(0, 1]; relative to the strongest corner",
        "corner_spacing_px": "[0, inf)",
        "window_px": "[3, inf); OpenCV's Lucas-Kanade needs a window wider than 2 px",
        "pyramid_levels": "[0, inf)",
        "max_fb_error_px": "(0, inf)",
    }


@dataclass(frozen=True)
class ReconstructionConfig:
    """Two-view near-planar reconstruction with metric scale."""

    method: Method = "rotation_aware"  # proposed | rotation_aware | classic | colmap | stereo
    features: FeatureConfig = field(default_factory=FeatureConfig)
    probe: ProbeConfig = field(default_factory=ProbeConfig)  # the fused run's cheap audit pair
    motion_prior: bool = True  # run the motion-prior mismatch rejection before RANSAC
    lambda_prior: float = 2.0  # λ: keep matches inside d̄ ± λ·σ_d per axis (eq. 4.7), unitless
    prior_min_halfwidth_px: float = (
        6.0  # floor of the λ window half-width (px): keeps real parallax
    )
    prior_min_halfwidth_frac: float = 0.12  # floor as a share of the median displacement |d̄| (0-1)
    prior_model: Literal["auto", "mean", "affine", "homography"] = "auto"  # centre d̄ of the
    # window (reconstruction.motion_prior): mean = constant (eq. 4.7 as published, R ≈ I, nadir),
    # affine = affine displacement field, homography = the road homography's field (any tilt:
    # a camera pitched 45° sees the road move 3x more at the image bottom than at the top);
    # auto = proposed: mean (the dissertation's method), rotation_aware: homography (on nadir
    # pairs it keeps and rejects at least what affine does, which beats mean under vibration)
    h_ransac_px: float = 3.0  # homography RANSAC reprojection threshold (px)
    h_ransac_frac: float = 0.03  # ... or this share of |d̄| if larger: depth relief up to ~3% of
    # the camera height still counts as planar (parallax scales with the displacement) (0-1)
    pose_model: Literal["plane_parallax", "select"] = "plane_parallax"  # rotation_aware's
    # final pose: plane_parallax = one generalised least squares over R, t and the road plane
    # with the relief as a random effect of estimated variance κσ² (no threshold); select =
    # the homography pose or the epipolar refinement, switched by planar_parallax_ratio
    planar_parallax_ratio: float = 2.0  # pose_model=select: keep the homography pose when the
    # H transfer error² / (4 · Sampson error²) is below this (parallax ≲ noise), else refine
    h_ransac_iters: int = 2000  # homography RANSAC max iterations (count)
    near_planar_max_outlier: float = 0.5  # pair is near-planar when H outlier ratio < this (0-1)
    f_ransac_px: float = 1.0  # classic baseline: fundamental-matrix RANSAC threshold (px)
    min_matches: int = 30  # fewer matches (after each filter) -> too_few_matches (count)
    min_displacement_px: float = 3.0  # median match displacement below this: the camera did not
    # move enough for depth (vehicle stopped) -> no_motion (px)
    min_features: int = 50  # fewer keypoints in a frame -> too_few_features (count)
    f_iterations: int = 10  # max iterations of the F = [e]x H rebuild loop (Fig. 3.4) (count)
    f_tol: float = 1e-9  # convergence of the rebuild loop: change of t direction (unitless)
    ba_iterations: int = 50  # rotation_aware: max least-squares evaluations x n_params (count)
    epi_inlier_px: float = 2.0  # keep matches whose Sampson distance to the final F is below (px)
    plane_trim_k: float = 3.0  # robust plane fit: refit without points > k MAD-sigmas off (0 = LS)
    colmap_max_error_px: float = 2.0  # pycolmap two-view RANSAC max error (px)
    pixel_sigma_px: float = 0.5  # σ: pixel noise for the first-order covariance (px)
    estimate_sigma: bool = True  # use σ̂ = 1.4826·MAD of the pair's Sampson residuals instead
    # (adaptive to each camera/texture; pixel_sigma_px is then the fallback for < 8 points)
    max_reproj_px: float = 4.0  # drop triangulated points with a larger reprojection error (px)
    stereo_baseline_m: float = 0.2  # stereo baseline B (m), dissertation Fig. 3.12
    min_overlap: float = 0.1  # matched area share of image a below this -> no_overlap (0-1)
    normal_consensus: bool = True  # after all pairs: re-solve pairs whose road normal is far
    # from the drive's (camera.yaml mount, else the pairs' majority) when their other homography
    # decomposition is near it, fail those with none near (reconstruction.consensus)
    rolling_shutter: bool = True  # move each observation to its frame's timestamp when the
    # camera has a rolling shutter (Camera.readout_s > 0; reconstruction.rolling_shutter);
    # False treats every camera as a global shutter
    rs_iterations: int = 6  # max re-estimates of the rolling-shutter correction (count)
    rs_tol_px: float = 0.02  # ... stopped once the correction changes by less than this (px)
    workers: int = 2  # threads extracting features ahead of the pair being solved (count)
    overwrite: bool = False  # recompute cached RUN/pairs and RUN/features files
    save_features: bool = True  # cache per-frame features in RUN/features/

    RANGES: ClassVar[dict[str, str]] = {
        "lambda_prior": "(0, inf)",
        "prior_min_halfwidth_px": "[0, inf)",
        "prior_min_halfwidth_frac": "[0, 1]",
        "prior_model": "{auto, mean, affine, homography}",
        "h_ransac_px": "(0, inf)",
        "h_ransac_frac": "[0, 1]",
        "planar_parallax_ratio": "(0, inf)",
        "h_ransac_iters": "[1, inf)",
        "near_planar_max_outlier": "[0, 1]",
        "f_ransac_px": "(0, inf)",
        "min_matches": "[8, inf); a two-view pose needs at least 8 matches",
        "min_displacement_px": "[0, inf)",
        "min_features": "[0, inf)",
        "f_iterations": "[1, inf)",
        "f_tol": "(0, inf)",
        "ba_iterations": "[1, inf)",
        "epi_inlier_px": "(0, inf)",
        "plane_trim_k": "[0, inf); 0 = least squares",
        "colmap_max_error_px": "(0, inf)",
        "pixel_sigma_px": "(0, inf)",
        "max_reproj_px": "(0, inf)",
        "stereo_baseline_m": "(0, 10]; a stereo baseline above 10 m is a unit mistake (cm typed as m?)",
        "min_overlap": "[0, 1]",
        "rs_iterations": "[1, inf)",
        "rs_tol_px": "(0, inf)",
        "workers": "[1, inf)",
    }
