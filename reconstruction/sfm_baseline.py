"""Baseline: pycolmap incremental SfM over a whole drive, scaled by camera height, aligned to GPS.

``roadsurf sfm-baseline DRIVE --out OUT`` (``run(cfg, drive_dir, out_dir)``):

1. COLMAP steps, all in ``OUT/colmap/`` and resumable (each step is recorded in
   ``OUT/colmap/state.json`` with a fingerprint of its settings and is skipped when done):
   SIFT feature extraction on the drive's valid frames with the camera intrinsics of
   camera.yaml (PINHOLE, or OPENCV/FULL_OPENCV when ``dist`` is non-zero), sequential matching
   (``overlap`` neighbours), incremental mapping with the intrinsics held fixed. Every model
   the mapper makes is kept in ``OUT/colmap/sparse/<k>/``.
2. Scale, per model (dissertation eq. 3.31-3.34, applied per camera): for every registered
   image a robust plane is fitted to the 3D points it sees; d_c is the median camera-to-plane
   distance and α = h / d_c with h = camera.yaml ``height_m``. The vertical is the mean plane
   normal. Poses that disagree with their neighbours (heading jump > 20°, camera-to-road
   distance > 25% off) are dropped with a reason (the planar two-fold ambiguity shows up so).
3. Georeferencing, per model: with GPS, a robust 2D rigid (or similarity) fit of the levelled,
   scaled camera centres to the GPS ENU positions interpolated at the frame times (frames far
   off a good fit are dropped as bad poses); the vertical offset, and an along-track tilt when
   the GPS altitude is good enough to show one, from the GPS altitude. The largest model is
   used first, then every smaller model that the GPS can place adds the frames the larger ones
   lack. Without GPS: only the largest model, in a local metric frame (first camera at the
   origin, its forward direction along +y), ``crs`` null and no lat/lon exports.
4. Outputs in OUT, in the run-folder format of ``roadsurf run`` (docs/formats.md): cloud.ply,
   surface.tif, trajectory.geojson, report.json, plus poses.npz/reference.json (the mapping
   ``Trajectory`` artifact) so the evaluation tools read both runs the same way. residual_m is
   relative to a local robust quadric road surface fitted per model (3 x 3 cells of 1 m).

The residual rasteriser and local surface fit here are small local versions (a sparse cloud on
one grid); the mapping stage has its own dense, tiled ones (mapping/raster.py, surface.py).
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

from roadsurf.core.atomic import read_json, write_json_atomic
from roadsurf.core.config import to_dict
from roadsurf.core.errors import RoadsurfError
from roadsurf.core.geometry import (
    EnuReference,
    check_shape,
    enu_from_lla,
    heading_deg_from_world_rotation,
)
from roadsurf.io.drive import Camera, Drive, load_drive

log = logging.getLogger(__name__)


# =========================================================================== config


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
    local_fit_cell_m: float = 1.0  # cell of the local road-surface fit for residual_m (m)
    local_fit_inlier_m: float = 0.01  # points further than this from the local fit are not road (m)
    max_abs_residual_m: float = 0.25  # points further than this above/below the local road surface
    # are triangulation outliers or off-road objects (deep potholes are ~0.1-0.2 m) (m)
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
    # COLMAP's own (glog) output: as configured, or everything with `roadsurf -v`.
    verbose = log.isEnabledFor(logging.DEBUG)
    pycolmap.logging.minloglevel = 0 if verbose else int(cfg.colmap_log_level)
    db_path = colmap_dir / "database.db"
    sparse_dir = colmap_dir / "sparse"
    state = _State(colmap_dir / "state.json")
    names = [f.filename for f in drive.frames]
    image_dir = drive.root / "frames"
    model, params = _colmap_camera(drive.camera)
    timings: dict[str, float] = {}
    steps = ["features", "matches", "mapping"]

    # Image identity (size, mtime) is part of the fingerprint: a re-rendered or edited drive
    # with the same filenames must not reuse stale features.
    stats = [(f.path.stat().st_size, f.path.stat().st_mtime_ns) for f in drive.frames]
    fp_feat = _fingerprint(
        [
            names,
            stats,
            model,
            params,
            cfg.max_num_features,
            cfg.max_image_size,
            pycolmap.__version__,
        ]
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
        from tqdm import tqdm

        with tqdm(total=len(names), desc="COLMAP mapping", unit="img", leave=False) as bar:
            pycolmap.incremental_mapping(
                db_path, image_dir, tmp, opts, next_image_callback=lambda: bar.update(1)
            )
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
    missing: list[str],
    models: dict[int, Any],
    model_notes: dict[int, str],
    cfg: SfmBaselineConfig,
) -> dict[str, str]:
    """A reason for every valid frame in ``missing`` (not in the outputs). ``model_notes`` says
    why a model's images were not used (e.g. it could not be aligned to GPS)."""
    import pycolmap

    if not missing:
        return {}
    in_model: dict[str, list[int]] = {}
    for k, rec in models.items():
        for im in rec.images.values():
            if im.has_pose:
                in_model.setdefault(im.name, []).append(k)
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
            note = model_notes.get(k, "it was not used")
            reasons[n] = f"registered only in a second model (sparse/{k}, {size} images); {note}"
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
    from roadsurf.io.formats import LOCAL_CRS, GridSpec

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
    grid = GridSpec(crs or LOCAL_CRS, x0, y0, gsd, w, h)
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
    if g is None:
        raise ValueError(f"{drive.root}: no GPS log to align the SfM model to")
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


class _ModelRejected(Exception):
    """A COLMAP model that cannot be scaled or placed (the reason goes to the report)."""


@dataclass
class _ModelGeo:
    """One COLMAP model, scaled and placed in the ENU (or local) frame."""

    index: int
    frames: list[Any]  # Frames this model provides to the outputs (capture order)
    R_wc: np.ndarray  # (M, 3, 3) world_from_cam rotations
    c_w: np.ndarray  # (M, 3) camera centres (m)
    p_w: np.ndarray  # (K, 3) points (m)
    rgb: np.ndarray  # (K, 3) uint8
    scale: dict[str, Any]
    align: dict[str, Any]
    outliers: dict[str, str]  # filename -> why its pose was rejected


def _fit_vertical_tilt(
    c_h: np.ndarray, gps_enu: np.ndarray, ok: np.ndarray, cfg: SfmBaselineConfig
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Small rotation about the horizontal cross-track axis that makes the camera heights follow
    the GPS altitude along the track: dz = a + g·s (s = along-track metres), fitted robustly.
    (The cross-track tilt is unobservable from a near-straight track; it stays from the road
    normal.) Used only when it explains the altitudes clearly better than a constant offset
    and stays under ``gps_tilt_max_deg``; consumer GPS altitude is too noisy to pass.
    Returns (R (3, 3), pivot (3,), tilt degrees) or None."""
    if not cfg.gps_tilt_correction or ok.sum() < 5:
        return None
    xy = c_h[ok, :2]
    dz = gps_enu[ok, 2] - c_h[ok, 2]
    pivot = np.array([*xy.mean(axis=0), float(c_h[ok, 2].mean())])
    _, _, vt = np.linalg.svd(xy - pivot[:2], full_matrices=False)
    u = vt[0]  # along-track direction
    s_m = (xy - pivot[:2]) @ u
    if np.ptp(s_m) < 2.0:
        return None
    A = np.column_stack([np.ones_like(s_m), s_m])
    w = np.ones(len(s_m), bool)
    coef = np.zeros(2)
    for _ in range(4):
        coef, *_ = np.linalg.lstsq(A[w], dz[w], rcond=None)
        r = dz - A @ coef
        sig = 1.4826 * float(np.median(np.abs(r[w]))) + 1e-6
        new = np.abs(r) <= 3 * sig
        if new.sum() < 5 or np.array_equal(new, w):
            break
        w = new
    rms_tilt = float(np.sqrt(np.mean((dz - A @ coef)[w] ** 2)))
    rms_flat = float(np.sqrt(np.mean((dz - np.median(dz))[w] ** 2)))
    b, c = float(coef[1] * u[0]), float(coef[1] * u[1])
    tilt_deg = math.degrees(math.atan(abs(float(coef[1]))))
    if tilt_deg > cfg.gps_tilt_max_deg or rms_tilt > 0.5 * rms_flat:
        return None
    n_new = np.array([-b, -c, 1.0])
    R = _rotation_a_to_b(np.array([0.0, 0.0, 1.0]), n_new / np.linalg.norm(n_new))
    return R, pivot, tilt_deg


def _neighbour_heading_dev(head_deg: np.ndarray, k: int = 3) -> np.ndarray:
    """|heading - median heading of the k neighbours on each side| (degrees, (N,))."""
    n = len(head_deg)
    dev = np.zeros(n)
    for i in range(n):
        nb = [j for j in range(max(0, i - k), min(n, i + k + 1)) if j != i]
        if not nb:
            continue
        d = (head_deg[nb] - head_deg[i] + 180.0) % 360.0 - 180.0
        dev[i] = abs(float(np.median(d)))
    return dev


def _georeference_model(
    k: int,
    rec: Any,
    drive: Drive,
    cfg: SfmBaselineConfig,
    ref: EnuReference | None,
    claimed: set[str],
) -> _ModelGeo:
    """Scale one COLMAP model by the camera height (α = h / d_c), level it with the road
    normal, drop inconsistent poses, and place it on the GPS (2D fit) or in a local frame."""
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    reg = [f for f in drive.frames if f.filename in by_name]
    # COLMAP camera axes = ours (x right, y down the image, z along the optical axis)
    cam_from_world = np.stack([by_name[f.filename].cam_from_world().matrix() for f in reg])
    R_cw = cam_from_world[:, :, :3]
    centres = np.einsum("nji,nj->ni", R_cw, -cam_from_world[:, :, 3])

    pids = np.array(list(rec.points3D.keys()), dtype=np.int64)
    pts = np.array([rec.points3D[p].xyz for p in pids]).reshape(-1, 3)
    rgb = np.array([rec.points3D[p].color for p in pids], dtype=np.uint8).reshape(-1, 3)
    pid_row = {int(p): i for i, p in enumerate(pids)}
    img_id_name = {im.image_id: im.name for im in by_name.values()}

    # ---- per-image robust plane: d_c (model units) and the up direction (eq. 3.31-3.33)
    rng = np.random.default_rng(cfg.seed)
    d_c = np.full(len(reg), np.nan)
    normals = np.full((len(reg), 3), np.nan)
    plane_inl = []
    for i, f in enumerate(reg):
        rows = [pid_row[int(p.point3D_id)] for p in by_name[f.filename].points2D if p.has_point3D()]
        if len(rows) < cfg.min_plane_points:
            continue
        P = pts[rows]
        thr = cfg.plane_inlier_rel * float(np.median(np.linalg.norm(P - centres[i], axis=1)))
        n, d, inl = fit_plane_ransac(P, thr, cfg.plane_iterations, rng)
        dist = float(n @ centres[i] + d)
        if dist < 0:  # orient the normal from the road towards the camera (= up)
            n, dist = -n, -dist
        d_c[i], normals[i] = dist, n
        plane_inl.append(float(inl.mean()))
    has = np.isfinite(d_c)
    if not has.any():
        raise _ModelRejected(f"no image sees {cfg.min_plane_points} 3D points: no road plane")
    d_c_med = float(np.median(d_c[has]))
    alpha = drive.camera.height_m / d_c_med  # eq. 3.34
    up = np.nanmean(normals[has], axis=0)
    up /= np.linalg.norm(up)
    R_level = _rotation_a_to_b(up, np.array([0.0, 0.0, 1.0]))
    origin = centres[0]
    c_lv = alpha * (centres - origin) @ R_level.T
    p_lv = alpha * (pts - origin) @ R_level.T
    R_wc_lv = np.einsum("ij,nkj->nik", R_level, R_cw)  # R_level @ R_cw.T

    # ---- pose outliers: a flipped/ambiguous planar pose shows as a heading jump against its
    # neighbours or a camera-to-road distance far from the others
    head = np.array([heading_deg_from_world_rotation(R) for R in R_wc_lv])
    bad = _neighbour_heading_dev(head) > 20.0
    bad |= has & (np.abs(d_c / d_c_med - 1.0) > 0.25)
    outliers = {
        f.filename: (
            f"registered by COLMAP (sparse/{k}) but its pose is inconsistent: heading "
            f"{_neighbour_heading_dev(head)[i]:.0f}° off its neighbours, camera-to-road "
            f"distance {alpha * d_c[i]:.2f} m vs h = {drive.camera.height_m} m; dropped"
        )
        for i, f in enumerate(reg)
        if bad[i]
    }
    good = ~bad
    if good.sum() < 2:
        raise _ModelRejected("fewer than 2 consistent poses")

    scale = {
        "height_m": drive.camera.height_m,
        "d_c_model_median": d_c_med,
        "d_c_rel_spread": float(np.std(d_c[has]) / d_c_med),
        "alpha_m_per_unit": alpha,
        "planes_fitted": int(has.sum()),
        "plane_inlier_ratio_median": float(np.median(plane_inl)),
        "up_in_model": up.tolist(),
        "pose_outliers": int(bad.sum()),
    }

    # ---- placement
    align: dict[str, Any] = {"kind": "none"}
    gps_enu = None
    if ref is not None:
        times = np.array([f.timestamp_s for f in reg])
        gps_enu = _interp_gps_enu(drive, times, ref, cfg.max_gps_gap_s)
        ok = np.isfinite(gps_enu).all(axis=1) & good
        if ok.sum() < 2:
            if claimed:  # a secondary model that the GPS cannot place is not used
                raise _ModelRejected(f"only {int(ok.sum())} of its frames have GPS; cannot align")
            log.warning("GPS overlaps fewer than 2 registered frames; using a local frame")
            gps_enu = None
    if gps_enu is not None:
        ok = np.isfinite(gps_enu).all(axis=1) & good
        sim = cfg.gps_fit == "similarity"
        R2, t2, s2, inl2 = robust_fit_2d(c_lv[ok, :2], gps_enu[ok, :2], sim, cfg.gps_outlier_k)
        _, _, s_sim, _ = robust_fit_2d(c_lv[ok, :2], gps_enu[ok, :2], True, cfg.gps_outlier_k)
        if sim:  # the GPS scale replaces α
            c_lv, p_lv = c_lv * s2, p_lv * s2
            scale["alpha_m_per_unit"] = alpha * s2
        R3 = np.eye(3)
        R3[:2, :2] = R2
        c_h = c_lv @ R3.T + np.array([*t2, 0.0])  # horizontally placed, not yet vertically
        p_h = p_lv @ R3.T + np.array([*t2, 0.0])
        tilt = _fit_vertical_tilt(c_h, gps_enu, ok & np.isfinite(gps_enu[:, 2]), cfg)
        if tilt is not None:
            R_t, pivot, tilt_deg = tilt
            c_h = (c_h - pivot) @ R_t.T + pivot
            p_h = (p_h - pivot) @ R_t.T + pivot
            R3 = R_t @ R3
        dz = float(np.median(gps_enu[ok, 2] - c_h[ok, 2]))
        c_w = c_h + [0.0, 0.0, dz]
        p_w = p_h + [0.0, 0.0, dz]
        z_res = gps_enu[ok, 2] - c_w[ok, 2]
        resid = np.linalg.norm(c_w[ok, :2] - gps_enu[ok, :2], axis=1)
        spread = float(np.ptp(gps_enu[ok, :2], axis=0).max())
        align = {
            "kind": f"2d_{cfg.gps_fit}",
            "n_frames_with_gps": int(ok.sum()),
            "n_inliers": int(inl2.sum()),
            "rms_m": float(np.sqrt(np.mean(resid[inl2] ** 2))),
            "max_m": float(resid.max()),
            "rotation_deg": float(math.degrees(math.atan2(R2[1, 0], R2[0, 0]))),
            "gps_scale_over_height_scale": float(s_sim) if not sim else 1.0,
            "gps_extent_m": spread,
            "vertical_offset_m": dz,
            "vertical_tilt_deg": tilt[2] if tilt is not None else 0.0,
            "vertical_rms_m": float(np.sqrt(np.mean(z_res**2))),
        }
        if spread < 2.0:
            log.warning("model %d: GPS positions span only %.1f m: weak 2D alignment", k, spread)
        # A pose far off a good GPS fit is a bad registration (e.g. the planar two-fold
        # ambiguity), not GPS noise: drop it like the heading/distance outliers above.
        rms_in = align["rms_m"]
        far = ~inl2 & (resid > max(3.0 * rms_in, cfg.gps_pose_outlier_min_m))
        for j, r_j in zip(np.flatnonzero(ok)[far], resid[far], strict=True):
            good[j] = False
            outliers[reg[j].filename] = (
                f"registered by COLMAP (sparse/{k}) but {r_j:.2f} m off the GPS fit of its "
                f"model (rms {rms_in:.3f} m); dropped as a bad pose"
            )
        align["pose_outliers_dropped"] = int(far.sum())
    else:
        # Local frame: first camera at the origin, its forward (-y camera axis) along +y.
        fwd = -R_wc_lv[0][:, 1]
        ang = math.atan2(fwd[0], fwd[1])  # rotate the forward azimuth onto north
        c, s_ = math.cos(ang), math.sin(ang)
        R3 = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        c_w, p_w = c_lv @ R3.T, p_lv @ R3.T
    R_wc = np.einsum("ij,njk->nik", R3, R_wc_lv)

    # ---- what this model contributes: consistent frames no larger model already gave, and
    # the points those frames observe
    use = np.array([good[i] and f.filename not in claimed for i, f in enumerate(reg)])
    if not use.any():
        raise _ModelRejected("all its consistent frames are already in a larger model")
    use_ids = {
        im_id
        for im_id, nm in img_id_name.items()
        if nm in {reg[i].filename for i in np.flatnonzero(use)}
    }
    keep = np.array(
        [any(el.image_id in use_ids for el in rec.points3D[int(p)].track.elements) for p in pids],
        dtype=bool,
    )
    return _ModelGeo(
        index=k,
        frames=[reg[i] for i in np.flatnonzero(use)],
        R_wc=R_wc[use],
        c_w=c_w[use],
        p_w=p_w[keep],
        rgb=rgb[keep],
        scale=scale,
        align=align,
        outliers=outliers,
    )


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
    from roadsurf.io.formats import write_geotiff
    from roadsurf.mapping.export import export_xyz, write_cloud_ply, write_trajectory_geojson
    from roadsurf.mapping.types import Trajectory, save_trajectory

    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    drive = load_drive(drive_dir)
    names = [f.filename for f in drive.frames]
    timings: dict[str, float] = {"load_s": time.perf_counter() - t_start}

    models, colmap_t = _run_colmap(cfg, drive, out / "colmap", overwrite)
    timings.update(colmap_t)
    t0 = time.perf_counter()
    sizes = {k: m.num_reg_images() for k, m in models.items()}
    order = sorted(sizes, key=lambda k: (-sizes[k], k))  # largest model first

    ref: EnuReference | None = None
    if drive.gps is not None and len(drive.gps) >= 2:
        g = drive.gps
        alt0 = float(g.alt_m[np.isfinite(g.alt_m)][0]) if np.isfinite(g.alt_m).any() else 0.0
        ref = EnuReference(float(g.lat_deg[0]), float(g.lon_deg[0]), alt0)
    elif drive.gps is None:
        drive.warnings.append("no GPS: outputs are in a local metric frame (crs null)")

    claimed: set[str] = set()
    parts: list[_ModelGeo] = []
    notes: dict[int, str] = {}
    outlier_reasons: dict[str, str] = {}
    for k in order:
        if sizes[k] < 2:
            notes[k] = "the model has fewer than 2 images"
            continue
        if parts and ref is None:
            notes[k] = "without GPS only the largest model can be placed (local frame)"
            continue
        try:
            geo = _georeference_model(k, models[k], drive, cfg, ref, claimed)
        except _ModelRejected as e:
            notes[k] = str(e)
            log.info("model %d (%d images) not used: %s", k, sizes[k], e)
            continue
        if ref is not None and not parts and geo.align.get("kind") == "none":
            ref = None  # GPS does not overlap the main model: local frame for everything
        outlier_reasons.update(geo.outliers)
        claimed.update(f.filename for f in geo.frames)
        parts.append(geo)
        if ref is None:
            break
    names_out = {f.filename for g2 in parts for f in g2.frames}
    missing = [n for n in names if n not in names_out]
    reasons = _not_registered_reasons(
        out / "colmap" / "database.db",
        [n for n in missing if n not in outlier_reasons],
        models,
        notes,
        cfg,
    )
    reasons.update({n: r for n, r in outlier_reasons.items() if n not in names_out})
    reasons = {n: reasons[n] for n in names if n in reasons}  # capture order
    if not parts:
        raise RoadsurfError(
            f"{drive.root}: pycolmap produced no usable model ({len(models)} models, sizes "
            f"{sizes}). Check the overlap between frames (speed vs fps) and the image texture. "
            + "; ".join(f"{n}: {r}" for n, r in list(reasons.items())[:5])
        )
    main = parts[0]

    # ---------------------------------------------------------------- merge the models
    frames_all = [f for g2 in parts for f in g2.frames]
    idx = np.argsort([f.index for f in frames_all], kind="stable")
    reg = [frames_all[i] for i in idx]
    R_wc = np.concatenate([g2.R_wc for g2 in parts])[idx]
    c_w = np.concatenate([g2.c_w for g2 in parts])[idx]
    times = np.array([f.timestamp_s for f in reg])

    # ---------------------------------------------------------------- points: clean, residual
    # Per model: each model has its own small vertical tilt/offset error, so the local road
    # surface is fitted to one model's points at a time (mixing layers would corrupt it).
    pw_l, rgb_l, res_l = [], [], []
    for g2 in parts:
        near = np.zeros(len(g2.p_w), bool)
        for i in range(0, len(g2.c_w), 64):  # chunked distance check against the cameras
            dd = np.linalg.norm(g2.p_w[:, None, :] - g2.c_w[None, i : i + 64, :], axis=2)
            near |= dd.min(axis=1) <= cfg.max_point_dist_m
        res_k, fitted = local_surface_residuals(
            g2.p_w[near], cfg.local_fit_cell_m, cfg.local_fit_inlier_m, cfg.local_fit_order
        )
        fitted &= np.abs(np.nan_to_num(res_k, nan=np.inf)) <= cfg.max_abs_residual_m
        pw_l.append(g2.p_w[near][fitted])
        rgb_l.append(g2.rgb[near][fitted])
        res_l.append(res_k[fitted])
    p_w = np.concatenate(pw_l)
    rgb = np.concatenate(rgb_l)
    residual = np.concatenate(res_l)
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
            "model_used": main.index,
            "models_used": [g2.index for g2 in parts],
            "points": int(len(p_w)),
            "surface_px_observed": int(np.isfinite(raster).sum()),
        },
        "registered": len(reg),
        "n_images": len(names),
        "not_registered_reason": reasons,
        "skipped": [{"file": s.file, "line": s.line, "reason": s.reason} for s in drive.skipped],
        "warnings": list(drive.warnings),
        "scale": main.scale,
        "gps_alignment": main.align,
        "models": [
            {
                "index": g2.index,
                "registered": int(sizes[g2.index]),
                "used_frames": len(g2.frames),
                "scale": g2.scale,
                "gps_alignment": g2.align,
            }
            for g2 in parts
        ],
        "models_not_used": {str(k): v for k, v in notes.items()},
        "surface": {"gsd_m": grid.gsd_m, "width": grid.width, "height": grid.height},
        "colmap": {
            "mean_reprojection_error_px": float(
                models[main.index].compute_mean_reprojection_error()
            ),
            "mean_track_length": float(models[main.index].compute_mean_track_length()),
            "camera_model": _colmap_camera(drive.camera)[0],
        },
        "config": to_dict(cfg),
        "timings_s": timings,
        "versions": _software_versions(),
    }
    write_json_atomic(out / "report.json", report)
    log.info(
        "sfm-baseline: %d/%d images in the outputs (models used %s of %d), α = %.4f m/unit, "
        "%d points, GPS fit rms %s m -> %s",
        len(reg),
        len(names),
        [g2.index for g2 in parts],
        len(models),
        main.scale["alpha_m_per_unit"],
        len(p_w),
        f"{main.align['rms_m']:.3f}" if "rms_m" in main.align else "n/a",
        out,
    )
    return SfmBaselineResult(
        out, len(names), len(reg), reasons, main.scale["alpha_m_per_unit"], crs, report
    )


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

    from roadsurf.core.config import from_dict
    from roadsurf.core.errors import ConfigError

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
