"""Settings and result of the pycolmap SfM baseline (``roadsurf sfm-baseline``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal


@dataclass(frozen=True)
class SfmBaselineConfig:
    """pycolmap incremental-SfM baseline. Units in the comments; α = h / d_c (eq. 3.34)."""

    max_num_features: int = 3000  # SIFT keypoints per image (count)
    max_image_size: int = 1600  # longer image side for SIFT extraction (px); larger are resized
    overlap: int = 5  # sequential matching: each frame is matched to this many successors (count)
    min_num_inliers: int = 15  # two-view verification: fewer inliers -> pair rejected (count)
    min_num_matches: int = 15  # mapper: pairs with fewer verified matches are ignored (count)
    init_min_tri_angle_deg: float = 8.0  # mapper initial pair min triangulation angle (degrees)
    num_threads: int = -1  # COLMAP threads (-1 = all cores)
    seed: int = 0  # COLMAP random seed (RANSAC, mapper) for repeatable runs
    plane_inlier_rel: float = 0.01  # plane RANSAC inlier threshold as a share of the median
    # camera-to-point distance (unitless); 1% of h ≈ 1 cm at h = 1.1 m
    plane_iterations: int = 200  # plane RANSAC iterations per image (count)
    min_plane_points: int = 12  # images seeing fewer 3D points get no plane / d_c (count)
    gps_fit: Literal["rigid", "similarity"] = "rigid"  # 2D fit of camera centres to GPS ENU:
    # rigid keeps the metric scale α from the camera height; similarity takes the scale from GPS
    gps_outlier_k: float = 3.0  # drop GPS fits with residual > k robust sigmas (unitless)
    gps_pose_outlier_min_m: float = 0.3  # a frame the robust GPS fit rejects is dropped as a bad
    # pose only when its residual also exceeds this (m): below it GPS noise can explain it
    gps_tilt_correction: bool = True  # tilt each model so its cameras follow the GPS altitude
    # when that explains the altitudes clearly better than a constant offset (RTK-grade logs)
    gps_tilt_max_deg: float = 5.0  # never tilt a model by more than this (degrees)
    max_gps_gap_s: float = 2.0  # frames further than this from a GPS fix get no GPS position (s)
    local_fit_cell_m: float = 0.5  # node spacing of the local road surface for residual_m (m)
    local_fit_window_m: float = 1.0  # side of the window of each node's robust plane fit (m)
    local_fit_inlier_m: float = 0.01  # points further than this from the local fit are not road (m)
    max_abs_residual_m: float = 0.25  # points further than this above/below the local road surface
    # are triangulation outliers or off-road objects (deep potholes are ~0.1-0.2 m) (m)
    max_point_dist_m: float = 5.0  # drop 3D points further than this from every camera (m)
    gsd_m: float = 0.02  # surface.tif pixel (m); SfM points are sparse, so coarser than `run`
    tile_px: int = 1024  # surface.tif lies on the tile lattice of `roadsurf run` (mapping
    # tile_px): origin on multiples of tile_px x gsd_m, so equal settings give equal cells (px)
    max_raster_px: int = 100_000_000  # coarsen the GSD when the raster would be larger (px)
    colmap_log_level: int = 1  # glog min level for COLMAP's own output: 0 info, 1 warning, 2 error

    # valid values (interval notation; see roadsurf.core.config)
    RANGES: ClassVar[dict[str, str]] = {
        "max_num_features": "[1, inf)",
        "max_image_size": "[16, inf)",
        "overlap": "[1, inf)",
        "min_num_inliers": "[0, inf)",
        "min_num_matches": "[0, inf)",
        "init_min_tri_angle_deg": "[0, 180)",
        "num_threads": "[-1, inf); -1 = all cores",
        "seed": "[0, 2147483647]",
        "plane_inlier_rel": "(0, 1]",
        "plane_iterations": "[1, inf)",
        "min_plane_points": "[3, inf); a plane needs 3 points",
        "gps_outlier_k": "(0, inf)",
        "gps_pose_outlier_min_m": "[0, inf)",
        "gps_tilt_max_deg": "[0, 90]",
        "max_gps_gap_s": "[0, inf)",
        "local_fit_cell_m": "(0, inf)",
        "local_fit_window_m": "(0, inf)",
        "local_fit_inlier_m": "(0, inf)",
        "max_abs_residual_m": "(0, inf)",
        "max_point_dist_m": "(0, inf)",
        "gsd_m": "(0, 1]; a raster cell above 1 m is a unit mistake (cm typed as m?)",
        "tile_px": "[16, 65536]; smaller tiles would be millions of files",
        "max_raster_px": "[1, inf)",
        "colmap_log_level": "[0, 3]; glog: 0 info, 1 warning, 2 error, 3 fatal",
    }


@dataclass
class SfmBaselineResult:
    out_dir: Path
    n_images: int  # valid frames given to COLMAP
    n_registered: int  # registered in the model that was used
    not_registered: dict[str, str]  # filename -> reason
    alpha: float  # metric scale α = h / d_c (m per model unit)
    crs: str | None
    report: dict[str, Any] = field(default_factory=dict)


def load_config(config_path: str | Path | None) -> SfmBaselineConfig:
    """The defaults, or a YAML file with an ``sfm_baseline:`` section (or the keys of
    ``SfmBaselineConfig`` at top level); unknown keys are rejected."""
    from roadsurf.core.config import from_dict, read_yaml_mapping

    cfg = SfmBaselineConfig()
    if config_path is not None:
        p = Path(config_path)
        data = read_yaml_mapping(p) or {}
        if isinstance(data, dict) and "sfm_baseline" in data:
            data = data["sfm_baseline"]
        cfg = from_dict(SfmBaselineConfig, data, f"{p}:sfm_baseline")
    return cfg
