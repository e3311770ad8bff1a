"""Baseline: pycolmap incremental SfM over a whole drive, scaled by camera height, aligned to GPS.

``roadsurf sfm-baseline DRIVE --out OUT`` (``run(cfg, drive_dir, out_dir)``):

1. COLMAP steps, all in ``OUT/colmap/`` and resumable (each step is recorded in
   ``OUT/colmap/state.json`` with a fingerprint of its settings and is skipped when done):
   SIFT feature extraction on the drive's valid frames with the camera intrinsics of
   camera.yaml (PINHOLE, or OPENCV/FULL_OPENCV when ``dist`` is non-zero), sequential matching
   (``overlap`` neighbours), incremental mapping with the intrinsics held fixed. Every model
   the mapper makes is kept in ``OUT/colmap/sparse/<k>/``; the largest is used.
2. Scale (dissertation eq. 3.31-3.34, applied per camera): for every registered image, a
   robust plane is fitted to the 3D points it sees; d_c is the median camera-to-plane distance
   and α = h / d_c with h = camera.yaml ``height_m``. The vertical is the mean plane normal.
3. Georeferencing: with GPS, a robust 2D rigid (or similarity) fit of the levelled, scaled
   camera centres to the GPS ENU positions interpolated at the frame times; the vertical offset
   from the GPS altitude when logged. Without GPS: a local metric frame (first camera at the
   origin, its forward direction along +y), ``crs`` null and no lat/lon exports.
4. Outputs in OUT, in the run-folder format of ``roadsurf run`` (docs/formats.md): cloud.ply,
   surface.tif, trajectory.geojson, report.json, plus poses.npz/reference.json (the mapping
   ``Trajectory`` artifact) so the evaluation tools read both runs the same way.

The residual rasteriser and local surface fit here are small local versions; the mapping stage
has its own (denser) ones.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from roadsurf.config import to_dict
from roadsurf.drive import Camera, Drive, load_drive
from roadsurf.errors import RoadsurfError
from roadsurf.geometry import (
    EnuReference,
    check_shape,
    enu_from_lla,
)
from roadsurf.io import read_json, write_json_atomic

log = logging.getLogger(__name__)


# =========================================================================== config


@dataclass(frozen=True)
class SfmBaselineConfig:
    """pycolmap incremental-SfM baseline. Units in the comments; α = h / d_c (eq. 3.34)."""

    max_num_features: int = 4096  # SIFT keypoints per image (count)
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
    max_gps_gap_s: float = 2.0  # frames further than this from a GPS fix get no GPS position (s)
    local_fit_cell_m: float = 1.0  # cell of the local road-surface fit for residual_m (m)
    local_fit_inlier_m: float = 0.01  # points further than this from the local fit are not road (m)
    local_fit_order: int = 2  # 1: plane, 2: quadric (follows camber/undulation), per 3x3 cells
    max_point_dist_m: float = 5.0  # drop 3D points further than this from every camera (m)
    gsd_m: float = 0.02  # surface.tif pixel (m); SfM points are sparse, so coarser than `run`
    max_raster_px: int = 100_000_000  # coarsen the GSD when the raster would be larger (px)
    colmap_log_level: int = 1  # glog min level for COLMAP's own output: 0 info, 1 warning, 2 error


# =========================================================================== results


@dataclass
class SfmBaselineResult:
    out_dir: Path
    n_images: int  # valid frames given to COLMAP
    n_registered: int  # registered in the model that was used
    not_registered: dict[str, str]  # filename -> reason
    alpha: float  # metric scale α = h / d_c (m per model unit)
    crs: str | None
    report: dict[str, Any] = field(default_factory=dict)


# =========================================================================== COLMAP steps


def _colmap_camera(cam: Camera) -> tuple[str, str]:
    """camera.yaml -> (COLMAP model name, params string). COLMAP puts the pixel origin at the
    top-left *corner* of the first pixel; ours is at its centre, hence +0.5 on cx, cy."""
    cx, cy = cam.cx + 0.5, cam.cy + 0.5
    k1, k2, p1, p2, k3 = cam.dist
    if not cam.has_distortion:
        return "PINHOLE", f"{cam.fx},{cam.fy},{cx},{cy}"
    if k3 == 0.0:
        return "OPENCV", f"{cam.fx},{cam.fy},{cx},{cy},{k1},{k2},{p1},{p2}"
    return "FULL_OPENCV", f"{cam.fx},{cam.fy},{cx},{cy},{k1},{k2},{p1},{p2},{k3},0,0,0"


def _fingerprint(obj: Any) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


class _State:
    """OUT/colmap/state.json: which COLMAP steps finished, with the settings they used."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data: dict[str, str] = read_json(path) if path.is_file() else {}

    def done(self, step: str, fp: str) -> bool:
        return self.data.get(step) == fp

    def mark(self, step: str, fp: str) -> None:
        self.data[step] = fp
        write_json_atomic(self.path, self.data)

    def invalidate_from(self, steps: list[str]) -> None:
        for s in steps:
            self.data.pop(s, None)
        write_json_atomic(self.path, self.data)


def _run_colmap(
    cfg: SfmBaselineConfig, drive: Drive, colmap_dir: Path, overwrite: bool
) -> tuple[dict[int, Any], dict[str, float]]:
    """Run (or resume) extraction, matching and mapping. Returns ({model index: Reconstruction},
    timings in seconds)."""
    import pycolmap

    if overwrite and colmap_dir.exists():
        shutil.rmtree(colmap_dir)
    colmap_dir.mkdir(parents=True, exist_ok=True)
    pycolmap.logging.minloglevel = int(cfg.colmap_log_level)
    db_path = colmap_dir / "database.db"
    sparse_dir = colmap_dir / "sparse"
    state = _State(colmap_dir / "state.json")
    names = [f.filename for f in drive.frames]
    image_dir = drive.root / "frames"
    model, params = _colmap_camera(drive.camera)
    timings: dict[str, float] = {}
    steps = ["features", "matches", "mapping"]

    fp_feat = _fingerprint(
        [names, model, params, cfg.max_num_features, cfg.max_image_size, pycolmap.__version__]
    )
    if not state.done("features", fp_feat):
        state.invalidate_from(steps)
        if db_path.exists():
            db_path.unlink()  # a half-written database from a killed run is not trusted
        log.info("COLMAP: extracting SIFT features from %d images", len(names))
        t = time.perf_counter()
        reader = pycolmap.ImageReaderOptions(camera_model=model, camera_params=params)
        ext = pycolmap.FeatureExtractionOptions()
        ext.sift.max_num_features = cfg.max_num_features
        ext.max_image_size = cfg.max_image_size
        ext.num_threads = cfg.num_threads
        pycolmap.extract_features(
            db_path,
            image_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=ext,
            device=pycolmap.Device.cpu,
        )
        timings["features_s"] = time.perf_counter() - t
        state.mark("features", fp_feat)
    else:
        log.info("COLMAP: features already extracted (resume)")

    fp_match = _fingerprint([fp_feat, cfg.overlap, cfg.min_num_inliers, cfg.seed])
    if not state.done("matches", fp_match):
        state.invalidate_from(steps[1:])
        with pycolmap.Database.open(db_path) as db:  # drop partial matches of a killed run
            db.clear_matches()
            db.clear_two_view_geometries()
        log.info("COLMAP: sequential matching (overlap %d)", cfg.overlap)
        t = time.perf_counter()
        mo = pycolmap.FeatureMatchingOptions()
        mo.num_threads = cfg.num_threads
        po = pycolmap.SequentialPairingOptions(overlap=cfg.overlap, quadratic_overlap=False)
        vo = pycolmap.TwoViewGeometryOptions()
        vo.min_num_inliers = cfg.min_num_inliers
        vo.ransac.random_seed = cfg.seed
        pycolmap.match_sequential(
            db_path,
            matching_options=mo,
            pairing_options=po,
            verification_options=vo,
            device=pycolmap.Device.cpu,
        )
        timings["matching_s"] = time.perf_counter() - t
        state.mark("matches", fp_match)
    else:
        log.info("COLMAP: matches already computed (resume)")

    fp_map = _fingerprint([fp_match, cfg.min_num_matches, cfg.init_min_tri_angle_deg, cfg.seed])
    if not state.done("mapping", fp_map) or not sparse_dir.is_dir():
        state.invalidate_from(steps[2:])
        tmp = colmap_dir / "sparse.tmp"
        for p in (tmp, sparse_dir):
            if p.exists():
                shutil.rmtree(p)
        tmp.mkdir()
        log.info("COLMAP: incremental mapping")
        t = time.perf_counter()
        opts = pycolmap.IncrementalPipelineOptions()
        # Intrinsics come from camera.yaml: hold them fixed.
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
        opts.min_num_matches = cfg.min_num_matches
        opts.mapper.init_min_tri_angle = cfg.init_min_tri_angle_deg
        opts.num_threads = cfg.num_threads
        opts.random_seed = cfg.seed
        opts.min_model_size = 3
        pycolmap.set_random_seed(cfg.seed)
        pycolmap.incremental_mapping(db_path, image_dir, tmp, opts)
        tmp.rename(sparse_dir)  # atomic: a killed mapping leaves no sparse/ to trust
        timings["mapping_s"] = time.perf_counter() - t
        state.mark("mapping", fp_map)
    else:
        log.info("COLMAP: sparse models already exist (resume)")

    models: dict[int, Any] = {}
    for sub in sorted(sparse_dir.iterdir()) if sparse_dir.is_dir() else []:
        if sub.is_dir() and sub.name.isdigit():
            models[int(sub.name)] = pycolmap.Reconstruction(sub)
    return models, timings


def _not_registered_reasons(
    db_path: Path,
    names: list[str],
    models: dict[int, Any],
    main: int | None,
    cfg: SfmBaselineConfig,
) -> dict[str, str]:
    """A reason for every valid frame that is not in the main model."""
    import pycolmap

    in_model: dict[str, list[int]] = {}
    for k, rec in models.items():
        for im in rec.images.values():
            if im.has_pose:
                in_model.setdefault(im.name, []).append(k)
    main_names = set() if main is None else {n for n, ks in in_model.items() if main in ks}
    missing = [n for n in names if n not in main_names]
    if not missing:
        return {}
    with pycolmap.Database.open(db_path) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        id2name = {v: k for k, v in ids.items()}
        best: dict[str, tuple[int, str]] = {}
        pair_ids, tvgs = db.read_two_view_geometries()
        for pid, g in zip(pair_ids, tvgs, strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            n_in = len(g.inlier_matches)
            for x, y in ((a, b), (b, a)):
                nx = id2name.get(x)
                if nx is not None and n_in > best.get(nx, (-1, ""))[0]:
                    best[nx] = (n_in, id2name.get(y, "?"))
        n_kp = {n: db.num_keypoints_for_image(i) for n, i in ids.items()}
    reasons: dict[str, str] = {}
    for n in missing:
        if n not in ids:
            reasons[n] = "not imported into the COLMAP database (unreadable by COLMAP)"
        elif n_kp.get(n, 0) < cfg.min_num_inliers:
            reasons[n] = f"only {n_kp.get(n, 0)} SIFT features (textureless, blurred or dark?)"
        elif n in in_model:
            k = in_model[n][0]
            size = models[k].num_reg_images()
            reasons[n] = (
                f"registered only in a second model (sparse/{k}, {size} images), which is "
                f"smaller than the model used"
            )
        elif best.get(n, (0, ""))[0] < cfg.min_num_matches:
            m, other = best.get(n, (0, ""))
            reasons[n] = (
                f"no verified two-view geometry with its {cfg.overlap} neighbours (best: "
                f"{m} inlier matches{' with ' + other if other else ''}); not in any model"
            )
        else:
            m, other = best[n]
            reasons[n] = (
                f"has {m} verified matches (with {other}) but the mapper could not register it "
                f"(absolute pose failed or too few triangulated points); not in any model"
            )
    return reasons


# =========================================================================== geometry helpers


def _fit_plane_lsq(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through (N, 3) points: unit normal n (3,) and offset d, n·x + d = 0."""
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    n = vt[-1]
    return n, -float(n @ c)


def fit_plane_ransac(
    pts: np.ndarray, thr: float, iterations: int, rng: np.random.Generator
) -> tuple[np.ndarray, float, np.ndarray]:
    """Robust plane: RANSAC (MSAC score) then least squares on the inliers.

    pts: (N, 3) points, thr: inlier distance (same unit). Returns (normal (3,), d, inlier mask (N,)).
    """
    pts = check_shape("pts", pts, (None, 3))
    n_pts = len(pts)
    if n_pts < 3:
        raise ValueError("a plane needs at least 3 points")
    best_cost, best = math.inf, None
    for _ in range(iterations):
        s = pts[rng.choice(n_pts, 3, replace=False)]
        nrm = np.cross(s[1] - s[0], s[2] - s[0])
        ln = np.linalg.norm(nrm)
        if ln < 1e-12:
            continue
        nrm /= ln
        r = np.abs(pts @ nrm - nrm @ s[0])
        cost = float(np.minimum(r, thr).sum())
        if cost < best_cost:
            best_cost, best = cost, (nrm, -float(nrm @ s[0]))
    if best is None:
        n, d = _fit_plane_lsq(pts)
    else:
        n, d = best
    inl = np.abs(pts @ n + d) < thr
    for _ in range(2):  # refine on the inliers
        if inl.sum() < 3:
            break
        n, d = _fit_plane_lsq(pts[inl])
        inl = np.abs(pts @ n + d) < thr
    return n, d, inl


def _rotation_a_to_b(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking unit vector a onto unit vector b (Rodrigues)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1 + 1e-12:  # opposite: rotate pi about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def fit_2d_transform(
    src: np.ndarray, dst: np.ndarray, with_scale: bool
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares 2D rigid/similarity (Umeyama): dst ≈ s R src + t.

    src, dst: (N, 2) metres. Returns (R (2, 2), t (2,), s)."""
    src = check_shape("src", src, (None, 2))
    dst = check_shape("dst", dst, (None, 2))
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    u, sv, vt = np.linalg.svd(cov)
    sign = np.diag([1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    R = u @ sign @ vt
    var_s = float((a**2).sum() / len(src))
    s = float(np.trace(np.diag(sv) @ sign) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def robust_fit_2d(
    src: np.ndarray, dst: np.ndarray, with_scale: bool, k: float
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Iteratively reweighted (trimmed) 2D fit: refit without pairs whose residual exceeds
    k robust sigmas (MAD). Returns (R, t, s, inlier mask (N,))."""
    inl = np.ones(len(src), bool)
    R, t, s = fit_2d_transform(src, dst, with_scale)
    for _ in range(5):
        r = np.linalg.norm(dst - (s * src @ R.T + t), axis=1)
        sigma = 1.4826 * float(np.median(r[inl])) + 1e-9
        new = r <= max(k * sigma, 1e-6)
        if new.sum() < 2 or np.array_equal(new, inl):
            break
        inl = new
        R, t, s = fit_2d_transform(src[inl], dst[inl], with_scale)
    return R, t, s, inl


def _poly_design(dx: np.ndarray, dy: np.ndarray, order: int) -> np.ndarray:
    cols = [np.ones_like(dx), dx, dy]
    if order >= 2:
        cols += [dx * dx, dx * dy, dy * dy]
    return np.column_stack(cols)


def local_surface_residuals(
    xyz: np.ndarray, cell_m: float, inlier_m: float, order: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Signed height of each point above a locally fitted road surface (negative below).

    For every occupied ``cell_m`` cell, a plane (``order`` 1) or quadric (``order`` 2) in x, y is
    fitted to the points of the 3 x 3 cells around it, trimming points further than
    ``inlier_m`` (and 3 robust sigmas) so that potholes do not pull the surface down; the
    quadric follows road camber and long-wave undulation over the 3-cell window. xyz: (N, 3)
    metres, z up. Returns (residual_m (N,), fitted (N,) bool; False where too few points)."""
    xyz = check_shape("xyz", xyz, (None, 3))
    res = np.full(len(xyz), np.nan)
    if len(xyz) == 0:
        return res, np.zeros(0, bool)
    n_min = 6 if order == 1 else 12
    ij = np.floor(xyz[:, :2] / cell_m).astype(np.int64)
    keys, inv = np.unique(ij, axis=0, return_inverse=True)
    inv = inv.ravel()
    order_idx = np.argsort(inv, kind="stable")
    starts = np.searchsorted(inv[order_idx], np.arange(len(keys) + 1))
    lookup = {tuple(k): c for c, k in enumerate(keys)}
    for c, (ci, cj) in enumerate(keys):
        nb = [
            order_idx[starts[o] : starts[o + 1]]
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
            if (o := lookup.get((ci + di, cj + dj))) is not None
        ]
        idx = np.concatenate(nb)
        if len(idx) < n_min:
            continue
        p = xyz[idx]
        cx, cy = (ci + 0.5) * cell_m, (cj + 0.5) * cell_m  # centre/scale for conditioning
        A = _poly_design((p[:, 0] - cx) / cell_m, (p[:, 1] - cy) / cell_m, order)
        w = np.ones(len(p), bool)
        coef = np.zeros(A.shape[1])
        for _ in range(5):
            coef, *_ = np.linalg.lstsq(A[w], p[w, 2], rcond=None)
            r = p[:, 2] - A @ coef
            sig = 1.4826 * float(np.median(np.abs(r[w]))) + 1e-6
            new = np.abs(r) <= min(inlier_m, 3 * sig) + 1e-6
            if new.sum() < n_min or np.array_equal(new, w):
                break
            w = new
        mine = order_idx[starts[c] : starts[c + 1]]
        q = xyz[mine]
        Aq = _poly_design((q[:, 0] - cx) / cell_m, (q[:, 1] - cy) / cell_m, order)
        res[mine] = q[:, 2] - Aq @ coef
    return res, np.isfinite(res)


def rasterise_mean(
    xy: np.ndarray, values: np.ndarray, gsd_m: float, max_px: int, crs: str | None
) -> tuple[np.ndarray, Any]:
    """Mean of ``values`` per cell of a north-up grid covering ``xy`` (N, 2) metres.

    Returns (float32 (H, W) raster, NaN where no point fell, GridSpec). The GSD is coarsened
    when the bounding grid would exceed ``max_px`` pixels."""
    from roadsurf.formats import GridSpec

    xy = check_shape("xy", xy, (None, 2))
    lo, hi = xy.min(0), xy.max(0)
    gsd = gsd_m
    while ((hi - lo) / gsd + 1).prod() > max_px:
        gsd *= 2
    if gsd != gsd_m:
        log.warning("surface raster: GSD coarsened from %.3f m to %.3f m (size cap)", gsd_m, gsd)
    x0 = math.floor(lo[0] / gsd) * gsd
    y0 = math.ceil(hi[1] / gsd) * gsd
    w = int(math.floor((hi[0] - x0) / gsd)) + 1
    h = int(math.floor((y0 - lo[1]) / gsd)) + 1
    grid = GridSpec(crs, x0, y0, gsd, w, h)  # type: ignore[arg-type]  # None: local frame
    col = np.clip(((xy[:, 0] - x0) / gsd).astype(np.int64), 0, w - 1)
    row = np.clip(((y0 - xy[:, 1]) / gsd).astype(np.int64), 0, h - 1)
    flat = row * w + col
    s = np.bincount(flat, weights=values, minlength=w * h)
    n = np.bincount(flat, minlength=w * h)
    out = np.full(w * h, np.nan, np.float32)
    ok = n > 0
    out[ok] = (s[ok] / n[ok]).astype(np.float32)
    return out.reshape(h, w), grid


# =========================================================================== main entry


def _interp_gps_enu(drive: Drive, times: np.ndarray, ref: EnuReference, max_gap_s: float):
    """GPS ENU (N, 3) at ``times`` (linear between fixes); NaN rows where no fix is near."""
    g = drive.gps
    assert g is not None  # noqa: S101 - caller checked
    alt = np.where(np.isfinite(g.alt_m), g.alt_m, ref.alt_m)
    enu = enu_from_lla(g.lat_deg, g.lon_deg, alt, ref)
    out = np.column_stack([np.interp(times, g.timestamp_s, enu[:, k]) for k in range(3)])
    # distance in time to the nearest fix; outside the log or in long gaps -> no position
    j = np.clip(np.searchsorted(g.timestamp_s, times), 1, len(g) - 1) if len(g) > 1 else None
    if j is None:
        gap = np.abs(times - g.timestamp_s[0])
        bracket = gap
    else:
        gap = np.minimum(np.abs(times - g.timestamp_s[j - 1]), np.abs(g.timestamp_s[j] - times))
        bracket = g.timestamp_s[j] - g.timestamp_s[j - 1]
    bad = (times < g.timestamp_s[0] - max_gap_s) | (times > g.timestamp_s[-1] + max_gap_s)
    bad |= (gap > max_gap_s) & (bracket > 2 * max_gap_s)
    out[bad] = np.nan
    return out


def _software_versions() -> dict[str, str]:
    import platform

    import pycolmap

    from roadsurf import __version__ as rv

    return {
        "roadsurf": rv,
        "pycolmap": pycolmap.__version__,
        "colmap": str(getattr(pycolmap, "COLMAP_version", "")),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def run(
    cfg: SfmBaselineConfig, drive_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False
) -> SfmBaselineResult:
    """Run the pycolmap baseline on a drive and write the run-folder outputs into ``out_dir``."""
    from mapping.export import export_xyz, write_cloud_ply, write_trajectory_geojson
    from mapping.types import Trajectory, save_trajectory
    from roadsurf.formats import write_geotiff

    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    drive = load_drive(drive_dir)
    names = [f.filename for f in drive.frames]
    timings: dict[str, float] = {"load_s": time.perf_counter() - t_start}

    models, colmap_t = _run_colmap(cfg, drive, out / "colmap", overwrite)
    timings.update(colmap_t)
    sizes = {k: m.num_reg_images() for k, m in models.items()}
    main = max(sizes, key=lambda k: (sizes[k], -k)) if sizes else None
    reasons = _not_registered_reasons(out / "colmap" / "database.db", names, models, main, cfg)
    if main is None or sizes[main] < 2:
        raise RoadsurfError(
            f"{drive.root}: pycolmap registered no model ({len(models)} models, sizes "
            f"{sizes}). Reasons per image are in the log; check overlap between frames "
            f"(speed vs fps) and image texture. Reasons: "
            + "; ".join(f"{n}: {r}" for n, r in list(reasons.items())[:5])
        )
    rec = models[main]
    t0 = time.perf_counter()

    # ---------------------------------------------------------------- registered cameras
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    reg = [f for f in drive.frames if f.filename in by_name]
    cam_from_world = np.stack(
        [by_name[f.filename].cam_from_world().matrix() for f in reg]
    )  # (M, 3, 4); COLMAP camera axes = ours (x right, y down the image, z optical axis)
    R_cw = cam_from_world[:, :, :3]
    centres = np.stack([-R_cw[i].T @ cam_from_world[i, :, 3] for i in range(len(reg))])

    # ---------------------------------------------------------------- points
    pids = np.array(list(rec.points3D.keys()), dtype=np.int64)
    pts = np.array([rec.points3D[p].xyz for p in pids]).reshape(-1, 3)
    rgb = np.array([rec.points3D[p].color for p in pids], dtype=np.uint8).reshape(-1, 3)
    pid_row = {int(p): i for i, p in enumerate(pids)}

    # ---------------------------------------------------------------- per-camera plane, d_c
    rng = np.random.default_rng(cfg.seed)
    d_c, normals, plane_inl = [], [], []
    for i, f in enumerate(reg):
        im = by_name[f.filename]
        rows = [pid_row[int(p.point3D_id)] for p in im.points2D if p.has_point3D()]
        if len(rows) < cfg.min_plane_points:
            continue
        P = pts[rows]
        thr = cfg.plane_inlier_rel * float(np.median(np.linalg.norm(P - centres[i], axis=1)))
        n, d, inl = fit_plane_ransac(P, thr, cfg.plane_iterations, rng)
        dist = float(n @ centres[i] + d)
        if dist < 0:  # orient the normal from the road towards the camera (= up)
            n, dist = -n, -dist
        d_c.append(dist)
        normals.append(n)
        plane_inl.append(float(inl.mean()))
    if not d_c:
        raise RoadsurfError(
            f"{drive.root}: no registered image sees {cfg.min_plane_points} 3D points; "
            f"cannot fit the road plane for the metric scale."
        )
    d_c_arr = np.asarray(d_c)
    d_c_med = float(np.median(d_c_arr))
    alpha = drive.camera.height_m / d_c_med  # eq. 3.34
    up = np.mean(normals, axis=0)
    up /= np.linalg.norm(up)
    R_level = _rotation_a_to_b(up, np.array([0.0, 0.0, 1.0]))
    origin = centres[0]

    def level(x: np.ndarray) -> np.ndarray:
        """model -> levelled, scaled, origin at the first camera (metres, z up)."""
        return alpha * (x - origin) @ R_level.T

    c_lv = level(centres)
    p_lv = level(pts)
    R_wc_lv = np.einsum("ij,njk->nik", R_level, np.transpose(R_cw, (0, 2, 1)))  # world_from_cam

    # ---------------------------------------------------------------- GPS alignment (2D)
    align: dict[str, Any] = {"kind": "none"}
    ref: EnuReference | None = None
    times = np.array([f.timestamp_s for f in reg])
    gps_enu = None
    if drive.gps is not None and len(drive.gps) >= 2:
        g = drive.gps
        alt0 = float(g.alt_m[np.isfinite(g.alt_m)][0]) if np.isfinite(g.alt_m).any() else 0.0
        ref = EnuReference(float(g.lat_deg[0]), float(g.lon_deg[0]), alt0)
        gps_enu = _interp_gps_enu(drive, times, ref, cfg.max_gps_gap_s)
        ok = np.isfinite(gps_enu).all(axis=1)
        if ok.sum() < 2:
            log.warning("GPS overlaps fewer than 2 registered frames; using a local frame")
            ref = None
    if ref is not None and gps_enu is not None:
        ok = np.isfinite(gps_enu).all(axis=1)
        R2, t2, s2, inl2 = robust_fit_2d(
            c_lv[ok, :2], gps_enu[ok, :2], cfg.gps_fit == "similarity", cfg.gps_outlier_k
        )
        _, _, s_sim, _ = robust_fit_2d(c_lv[ok, :2], gps_enu[ok, :2], True, cfg.gps_outlier_k)
        if cfg.gps_fit == "similarity":  # the GPS scale replaces α
            c_lv, p_lv = c_lv * s2, p_lv * s2
            alpha *= s2
        R3 = np.eye(3)
        R3[:2, :2] = R2
        xy_c = c_lv[:, :2] @ R2.T + t2
        dz = float(np.median(gps_enu[ok, 2] - c_lv[ok, 2]))
        shift = np.array([*t2, dz])
        c_w = np.column_stack([xy_c, c_lv[:, 2] + dz])
        p_w = p_lv @ R3.T + shift
        R_wc = np.einsum("ij,njk->nik", R3, R_wc_lv)
        resid = np.linalg.norm(c_w[ok, :2] - gps_enu[ok, :2], axis=1)
        spread = float(np.ptp(gps_enu[ok, :2], axis=0).max())
        align = {
            "kind": f"2d_{cfg.gps_fit}",
            "n_frames_with_gps": int(ok.sum()),
            "n_inliers": int(inl2.sum()),
            "rms_m": float(np.sqrt(np.mean(resid[inl2] ** 2))),
            "max_m": float(resid.max()),
            "rotation_deg": float(math.degrees(math.atan2(R2[1, 0], R2[0, 0]))),
            "gps_scale_over_height_scale": float(s_sim) if cfg.gps_fit == "rigid" else 1.0,
            "gps_extent_m": spread,
            "vertical_offset_m": dz,
        }
        if spread < 2.0:
            log.warning("GPS positions span only %.1f m: the 2D alignment is weak", spread)
    else:
        # Local frame: first camera at the origin, its forward (-y camera axis) along +y.
        fwd = -R_wc_lv[0][:, 1]
        ang = math.atan2(fwd[0], fwd[1])  # rotate the forward azimuth onto north
        c, s = math.cos(ang), math.sin(ang)
        R3 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        c_w, p_w = c_lv @ R3.T, p_lv @ R3.T
        R_wc = np.einsum("ij,njk->nik", R3, R_wc_lv)
        if drive.gps is None:
            drive.warnings.append("no GPS: outputs are in a local metric frame (crs null)")

    # ---------------------------------------------------------------- points: clean, residual
    near = np.zeros(len(p_w), bool)
    for i in range(0, len(c_w), 64):  # chunked distance check against every camera
        dd = np.linalg.norm(p_w[:, None, :] - c_w[None, i : i + 64, :], axis=2).min(axis=1)
        near |= dd <= cfg.max_point_dist_m
    p_w, rgb = p_w[near], rgb[near]
    residual, fitted = local_surface_residuals(
        p_w, cfg.local_fit_cell_m, cfg.local_fit_inlier_m, cfg.local_fit_order
    )
    p_w, rgb, residual = p_w[fitted], rgb[fitted], residual[fitted]
    timings["scale_align_s"] = time.perf_counter() - t0

    # ---------------------------------------------------------------- write outputs
    t0 = time.perf_counter()
    world_from_cam = np.tile(np.eye(4), (len(reg), 1, 1))
    world_from_cam[:, :3, :3] = R_wc
    world_from_cam[:, :3, 3] = c_w
    traj = Trajectory(
        filenames=[f.filename for f in reg],
        frame_indices=np.array([f.index for f in reg], dtype=np.int64),
        timestamp_s=times,
        world_from_cam=world_from_cam,
        source=["visual"] * len(reg),
        reference=ref,
    )
    save_trajectory(out, traj)
    ef = traj.export_frame
    crs = ef.crs if ef is not None else None
    write_cloud_ply(out / "cloud.ply", p_w, rgb, residual, ef)
    xy_out = export_xyz(p_w, ef)[:, :2]
    raster, grid = rasterise_mean(xy_out, residual, cfg.gsd_m, cfg.max_raster_px, crs)
    write_geotiff(
        out / "surface.tif",
        raster,
        grid,
        nodata=float("nan"),
        tags={"source": "roadsurf sfm-baseline", "units": "m, negative below the road"},
    )
    write_trajectory_geojson(out / "trajectory.geojson", traj, extra={"producer": "sfm-baseline"})
    timings["export_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start

    report: dict[str, Any] = {
        "producer": "roadsurf sfm-baseline",
        "drive": str(drive.root),
        "crs": crs,
        "reference": {**ref.to_dict(), "crs": crs} if ref is not None else None,
        "frame": "UTM (crs) for cloud.ply/surface.tif"
        if crs
        else "local metric frame (no GPS): x right of the first frame, y its forward, z up",
        "counts": {
            "frames": len(drive.frames),
            "n_images": len(names),
            "registered": len(reg),
            "models": {str(k): v for k, v in sorted(sizes.items())},
            "model_used": main,
            "points": int(len(p_w)),
            "surface_px_observed": int(np.isfinite(raster).sum()),
        },
        "registered": len(reg),
        "n_images": len(names),
        "not_registered_reason": reasons,
        "skipped": [{"file": s.file, "line": s.line, "reason": s.reason} for s in drive.skipped],
        "warnings": list(drive.warnings),
        "scale": {
            "height_m": drive.camera.height_m,
            "d_c_model_median": d_c_med,
            "d_c_rel_spread": float(np.std(d_c_arr) / d_c_med),
            "alpha_m_per_unit": alpha,
            "planes_fitted": len(d_c),
            "plane_inlier_ratio_median": float(np.median(plane_inl)),
            "up_in_model": up.tolist(),
        },
        "gps_alignment": align,
        "surface": {"gsd_m": grid.gsd_m, "width": grid.width, "height": grid.height},
        "colmap": {
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
            "mean_track_length": float(rec.compute_mean_track_length()),
            "camera_model": _colmap_camera(drive.camera)[0],
        },
        "config": to_dict(cfg),
        "timings_s": timings,
        "versions": _software_versions(),
    }
    write_json_atomic(out / "report.json", report)
    log.info(
        "sfm-baseline: %d/%d images registered (model %s of %d), α = %.4f m/unit, %d points, "
        "GPS fit rms %s m -> %s",
        len(reg),
        len(names),
        main,
        len(models),
        alpha,
        len(p_w),
        f"{align['rms_m']:.3f}" if "rms_m" in align else "n/a",
        out,
    )
    return SfmBaselineResult(out, len(names), len(reg), reasons, alpha, crs, report)


def run_from_paths(
    drive_dir: str | Path,
    out_dir: str | Path,
    *,
    config_path: str | Path | None = None,
    overwrite: bool = False,
) -> SfmBaselineResult:
    """CLI entry: load the config (a YAML file with an ``sfm_baseline:`` section, or the keys of
    ``SfmBaselineConfig`` at top level; unknown keys are rejected) and ``run``."""
    import yaml

    from roadsurf.config import from_dict
    from roadsurf.errors import ConfigError

    cfg = SfmBaselineConfig()
    if config_path is not None:
        p = Path(config_path)
        if not p.is_file():
            raise ConfigError(f"{p}: config file not found")
        try:
            data = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"{p}: not valid YAML ({e}). Fix the syntax.") from e
        if isinstance(data, dict) and "sfm_baseline" in data:
            data = data["sfm_baseline"]
        cfg = from_dict(SfmBaselineConfig, data, f"{p}:sfm_baseline")
    return run(cfg, drive_dir, out_dir, overwrite=overwrite)
