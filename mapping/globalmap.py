"""Global map: one continuous georeferenced cloud, residual surface raster and orthomosaic.

1. Every ok pair's metric points (camera a) go to ENU with the fused pose of frame a; colours are
   sampled from image a at ``px_a``.
2. Points seen by several pairs are fused in a voxel hash (``voxel_m``): mean position, colour,
   and the number of observations.
3. ``residual_m`` = signed height above a locally fitted road surface (``mapping.surface``;
   continuous, robust to defects), negative below.
4. Rasters on ONE grid (export CRS, GSD ``gsd_m``), only on tiles of a global lattice that the
   corridor passes: the residual surface (Delaunay interpolation of the fused points, extended
   by at most ``surface_fill_max_m`` towards the border of the part seen by both frames of an
   ok pair, holes elsewhere) and an RGB orthomosaic made by projecting every posed frame onto
   the fitted surface (``cv2.remap``) and blending with feathered weights, so seams do not
   show. Tiles are processed one at a time (memory grows with the tile size, not with the
   drive), written to ``tiles/`` + ``surface.vrt``/``mosaic.vrt``, and window by window into sparse
   ``surface.tif``/``mosaic.tif`` while the bounding grid stays below ``max_raster_px``.
5. ``cloud.ply`` (export CRS), ``map_points.npz`` (ENU, for detection), PNG previews.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from roadsurf.core.atomic import atomic_path, read_json, write_json_atomic, write_npz_atomic
from roadsurf.core.config import to_dict
from roadsurf.core.errors import FrameReadError
from roadsurf.core.parallel import SharedCache, ordered_map
from roadsurf.io.drive import Camera, Drive, Frame, read_image
from roadsurf.io.formats import GridSpec
from roadsurf.mapping.config import NOT_IN_FINGERPRINT, MappingConfig
from roadsurf.mapping.export import export_xyz, write_cloud_ply
from roadsurf.mapping.raster import (
    LOCAL_CRS,
    GridToEnu,
    TiledWriter,
    corridor_tiles,
    fill_nodata_capped,
    interpolate_to_grid,
)
from roadsurf.mapping.surface import LocalSurface
from roadsurf.mapping.types import Trajectory

log = logging.getLogger(__name__)

MAP_REPORT = "map_report.json"
NODATA_SURFACE = float("nan")


@dataclass
class MapProducts:
    """What the global-map stage wrote (paths relative to the run folder) and key figures."""

    run_dir: Path
    crs: str | None  # export CRS of cloud.ply and the rasters (None: local ENU frame)
    gsd_m: float
    n_points_raw: int = 0  # points from all ok pairs
    n_points: int = 0  # after voxel fusion
    n_tiles: int = 0
    grid: dict[str, Any] | None = None  # bounding grid of the tile lattice
    files: dict[str, str] = field(default_factory=dict)
    residual_stats_m: dict[str, float] = field(default_factory=dict)
    surface_px: int = 0  # observed pixels in surface.tif
    mosaic_px: int = 0  # imaged pixels in mosaic.tif
    patch_alignment: dict[str, float] = field(default_factory=dict)
    # share of each frame's road footprint the next frame also sees: median, 10th percentile
    frame_overlap: dict[str, float] = field(default_factory=dict)
    # non-empty tiles: row, col, bounds [x_min, y_min, x_max, y_max] in the grid CRS, and the
    # per-tile files when written, so readers can stay within the corridor (window by window)
    tiles: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)

    def to_report(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["run_dir"] = str(self.run_dir)
        return d

    @classmethod
    def from_report(cls, d: dict[str, Any]) -> MapProducts:
        d = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        d["run_dir"] = Path(d["run_dir"])
        return cls(**d)


# =========================================================================== entry point


def run(
    cfg: MappingConfig, drive: Drive, pairs: list[Any], traj: Trajectory, run_dir: str | Path
) -> MapProducts:
    """Build and write the global map products into ``run_dir`` (resumes when unchanged)."""
    run_dir = Path(run_dir)
    key = _fingerprint(cfg, pairs, traj)
    rep_path = run_dir / MAP_REPORT
    if not cfg.overwrite and rep_path.is_file():
        try:
            rep = read_json(rep_path)
            files = rep.get("files", {})
            if rep.get("fingerprint") == key and all(
                (run_dir / f).exists() for f in files.values()
            ):
                log.info("globalmap: inputs unchanged, reusing the map in %s", run_dir)
                return MapProducts.from_report(rep)
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.info("globalmap: cached report unreadable (%s); rebuilding", e)
    prod = build_map(cfg, drive, pairs, traj, run_dir)
    write_json_atomic(rep_path, {"fingerprint": key, **prod.to_report()})
    return prod


def _fingerprint(cfg: MappingConfig, pairs: list[Any], traj: Trajectory) -> str:
    h = hashlib.sha256()
    c = {k: v for k, v in to_dict(cfg).items() if k not in NOT_IN_FINGERPRINT}
    h.update(json.dumps(c, sort_keys=True, default=str).encode())
    h.update(np.ascontiguousarray(traj.world_from_cam, float).tobytes())
    for p in pairs:
        h.update(f"{p.index_a},{p.index_b},{p.status},{p.n_points}".encode())
    return h.hexdigest()[:16]


# =========================================================================== building


def build_map(
    cfg: MappingConfig, drive: Drive, pairs: list[Any], traj: Trajectory, run_dir: Path
) -> MapProducts:
    t0 = time.perf_counter()
    run_dir.mkdir(parents=True, exist_ok=True)
    ef = traj.export_frame
    crs = ef.crs if ef is not None else None
    prod = MapProducts(run_dir=run_dir, crs=crs, gsd_m=cfg.gsd_m)
    frames_by_index = {f.index: f for f in drive.frames}
    pose_of = {fn: i for i, fn in enumerate(traj.filenames)}

    # ---------------------------------------------------------------- 1-2 points, fused
    xyz, rgb, frame_idx, n_raw = _collect_points(cfg, drive, pairs, traj, frames_by_index, pose_of)
    prod.n_points_raw = n_raw
    if cfg.align_patches and len(xyz):
        xyz, prod.patch_alignment = align_patches(cfg, xyz, frame_idx)
    xyz, rgb, frame_idx, nobs = voxel_fuse(xyz, rgb, frame_idx, cfg.voxel_m)
    prod.timings_s["points"] = round(time.perf_counter() - t0, 3)

    # ---------------------------------------------------------------- 3 local road surface
    t1 = time.perf_counter()
    surf = LocalSurface(cfg, xyz)
    resid = surf.residual(xyz) if len(xyz) else np.zeros(0)
    keep = np.isfinite(resid)
    if (~keep).any():
        log.info("globalmap: %d isolated points without a local road fit dropped", (~keep).sum())
    xyz, rgb, frame_idx, nobs, resid = (
        xyz[keep],
        rgb[keep],
        frame_idx[keep],
        nobs[keep],
        resid[keep],
    )
    prod.n_points = len(xyz)
    prod.timings_s["surface_fit"] = round(time.perf_counter() - t1, 3)
    if len(resid):
        prod.residual_stats_m = {
            "p01": float(np.percentile(resid, 1)),
            "median": float(np.median(resid)),
            "p99": float(np.percentile(resid, 99)),
            "mad": float(1.4826 * np.median(np.abs(resid - np.median(resid)))),
        }

    # ---------------------------------------------------------------- 5 point products
    t2 = time.perf_counter()
    write_npz_atomic(
        run_dir / "map_points.npz",
        xyz=xyz,
        rgb=rgb,
        residual_m=resid.astype(np.float32),
        frame_index=frame_idx,
        n_obs=nobs,
    )
    prod.files["map_points"] = "map_points.npz"
    write_cloud_ply(
        run_dir / "cloud.ply", xyz, rgb, resid, ef, extra={"n_obs": nobs.astype(np.int32)}
    )
    prod.files["cloud"] = "cloud.ply"
    prod.timings_s["cloud"] = round(time.perf_counter() - t2, 3)

    # ---------------------------------------------------------------- 4 rasters
    t3 = time.perf_counter()
    # pose indices of the ok pairs: the surface exists only where both frames of one saw the road
    pair_frames = [
        (pose_of[p.frame_a], pose_of[p.frame_b])
        for p in pairs
        if p.ok and p.n_points > 0 and p.frame_a in pose_of and p.frame_b in pose_of
    ]
    _rasters(cfg, drive, traj, surf, xyz, resid, prod, frames_by_index, pair_frames)
    prod.timings_s["rasters"] = round(time.perf_counter() - t3, 3)
    prod.timings_s["total"] = round(time.perf_counter() - t0, 3)
    return prod


def _collect_points(
    cfg: MappingConfig,
    drive: Drive,
    pairs: list[Any],
    traj: Trajectory,
    frames_by_index: dict[int, Frame],
    pose_of: dict[str, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    xs, cs, fs = [], [], []
    ok = [p for p in pairs if p.ok and p.n_points > 0 and p.frame_a in pose_of]
    for p in tqdm(ok, desc="map points", unit="pair", leave=False):
        P = np.asarray(p.points_cam_a_m, float)
        good = np.all(np.isfinite(P), axis=1) & (P[:, 2] > 0) & (P[:, 2] < cfg.max_point_depth_m)
        if not good.any():
            continue
        P = P[good]
        W = traj.world_from_cam[pose_of[p.frame_a]]
        xs.append(P @ W[:3, :3].T + W[:3, 3])
        col = np.full((len(P), 3), 128, np.uint8)
        fr = frames_by_index.get(int(p.index_a))
        if cfg.colour_from_images and fr is not None:
            try:
                img = read_image(fr)
                px = np.asarray(p.px_a, float)[good]
                u = np.clip(np.round(px[:, 0]).astype(int), 0, img.shape[1] - 1)
                v = np.clip(np.round(px[:, 1]).astype(int), 0, img.shape[0] - 1)
                col = img[v, u]
            except (FrameReadError, OSError) as e:
                log.warning("globalmap: no colour for %s (%s)", fr.filename, e)
        cs.append(col)
        fs.append(np.full(len(P), int(p.index_a), np.int64))
    if not xs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int64), 0
    xyz = np.concatenate(xs)
    return xyz, np.concatenate(cs), np.concatenate(fs), len(xyz)


def align_patches(
    cfg: MappingConfig, xyz: np.ndarray, patch: np.ndarray, iterations: int = 4
) -> tuple[np.ndarray, dict[str, float]]:
    """Remove height seams between pair patches (a strip adjustment).

    Each point is compared with its nearest neighbours (within 2 cm) from OTHER patches, using
    residuals to the local road surface so that the road slope cancels. Each patch then gets a
    robust planar correction (offset + tilt; defect mismatches trimmed by MAD) of half the
    disagreement, so neighbouring patches meet in the middle (Jacobi iterations).
    Returns the corrected (N, 3) points and statistics of the applied offsets (m)."""
    from scipy.spatial import cKDTree

    xyz = xyz.copy()
    ids, inv = np.unique(patch, return_inverse=True)
    applied = np.zeros(len(ids))
    order = np.argsort(inv, kind="stable")
    bounds = np.searchsorted(inv[order], np.arange(len(ids) + 1))
    tree = cKDTree(xyz[:, :2])
    dist, nb = tree.query(xyz[:, :2], k=8, distance_upper_bound=0.02)
    valid_nb = np.isfinite(dist)
    nb = np.where(valid_nb, nb, 0)
    other = valid_nb & (inv[nb] != inv[:, None])
    for _ in range(iterations):
        surf = LocalSurface(cfg, xyz, progress=False)
        r = surf.residual(xyz)
        rn = np.where(other, r[nb], np.nan)
        with np.errstate(all="ignore"):
            cnt = np.sum(np.isfinite(rn), axis=1)
            ref = np.where(cnt > 0, np.nansum(rn, axis=1) / np.maximum(cnt, 1), np.nan)
        d = r - ref  # this point's height minus its neighbours' from other patches
        corr_all = np.zeros(len(xyz))
        for j in range(len(ids)):
            sel = order[bounds[j] : bounds[j + 1]]
            dd = d[sel]
            ok = np.isfinite(dd)
            if ok.sum() < 15:
                continue
            P = xyz[sel]
            c = P[ok, :2].mean(0)
            A = np.column_stack([np.ones(len(P)), P[:, 0] - c[0], P[:, 1] - c[1]])
            inl = ok.copy()
            coef = np.zeros(3)
            for _k in range(4):
                coef, *_ = np.linalg.lstsq(A[inl], dd[inl], rcond=None)
                e = np.where(ok, dd - A @ coef, np.inf)
                s = 1.4826 * np.median(np.abs(e[inl])) + 1e-6
                new = np.abs(e) < max(3 * s, 0.5 * cfg.local_fit_inlier_m)
                if new.sum() < 10 or np.array_equal(new, inl):
                    break
                inl = new
            if inl.sum() < 30:
                coef[1:] = 0.0  # too little overlap to estimate a tilt
            corr_all[sel] = 0.5 * (A @ coef)
            applied[j] += 0.5 * coef[0]
        xyz[:, 2] -= corr_all
    stats = {
        "patches": int(len(ids)),
        "offset_abs_median_m": float(np.median(np.abs(applied))) if len(ids) else 0.0,
        "offset_abs_max_m": float(np.max(np.abs(applied))) if len(ids) else 0.0,
    }
    return xyz, stats


def voxel_fuse(
    xyz: np.ndarray, rgb: np.ndarray, frame_idx: np.ndarray, voxel_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fuse points in the same voxel (numpy hash): mean xyz and colour, first frame index, and
    the observation count. Returns (xyz (M,3), rgb (M,3) uint8, frame (M,), n_obs (M,))."""
    if len(xyz) == 0 or voxel_m <= 0:
        return xyz, rgb, frame_idx, np.ones(len(xyz), np.int64)
    q = np.floor((xyz - xyz.min(0)) / voxel_m).astype(np.int64)
    dims = q.max(0) + 1
    key = (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    m = len(cnt)
    out = np.zeros((m, 3))
    col = np.zeros((m, 3))
    for j in range(3):
        out[:, j] = np.bincount(inv, weights=xyz[:, j], minlength=m) / cnt
        col[:, j] = np.bincount(inv, weights=rgb[:, j].astype(float), minlength=m) / cnt
    first = np.full(m, np.iinfo(np.int64).max)
    np.minimum.at(first, inv, frame_idx)
    return out, np.clip(np.round(col), 0, 255).astype(np.uint8), first, cnt.astype(np.int64)


# =========================================================================== camera model


def project(camera: Camera, X_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (..., 3) -> distorted pixel u, v (...). Z <= 0 gives NaN."""
    Z = X_cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(Z > 1e-6, X_cam[..., 0] / Z, np.nan)
        y = np.where(Z > 1e-6, X_cam[..., 1] / Z, np.nan)
    if camera.has_distortion:
        k1, k2, p1, p2, k3 = camera.dist
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = (
            x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
        )
    return camera.fx * x + camera.cx, camera.fy * y + camera.cy


def consecutive_overlap(footprints_xy_m: list[np.ndarray]) -> np.ndarray:
    """(N-1,) share of frame i's road footprint that frame i+1 also sees (0-1; NaN where a
    footprint is missing). ``footprints_xy_m``: N arrays (K, 2) of footprint points (m), e.g.
    ``footprint_enu``'s grid; each footprint is their convex hull."""
    import shapely

    hulls = [
        shapely.MultiPoint(np.asarray(f, float)).convex_hull if len(f) >= 3 else None
        for f in footprints_xy_m
    ]
    out = np.full(max(0, len(hulls) - 1), np.nan)
    for i in range(len(out)):
        a, b = hulls[i], hulls[i + 1]
        if a is not None and b is not None and a.area > 0:
            out[i] = a.intersection(b).area / a.area
    return out


def _check_frame_overlap(cfg: MappingConfig, fp_grid: list[np.ndarray], prod: MapProducts) -> None:
    """Record the consecutive-frame overlap and warn when it is below ``min_frame_overlap``:
    below half, the two-view parts of consecutive pairs no longer touch and the map is strips."""
    ov = consecutive_overlap(fp_grid)
    ov = ov[np.isfinite(ov)]
    if not len(ov):
        return
    med = float(np.median(ov))
    prod.frame_overlap = {"median": round(med, 3), "p10": round(float(np.percentile(ov, 10)), 3)}
    if med < cfg.min_frame_overlap:
        msg = (
            f"consecutive frames overlap by only {med:.0%} (median; below "
            f"{cfg.min_frame_overlap:.0%}): 3D comes from the overlaps, so the map is strips "
            "with unmeasured road between them, defects there are missed and long ones are "
            "measured in pieces. Drive slower or raise the frame rate (overlap = 1 - speed / "
            "(frame rate x footprint length along the drive))"
        )
        log.warning("globalmap: %s", msg)
        prod.warnings.append(msg)


def footprint_enu(camera: Camera, W: np.ndarray, road_z: float, n: int = 5) -> np.ndarray:
    """(n*n, 3) ENU points where an n×n grid of image pixels meets the plane z = road_z."""
    u = np.linspace(0, camera.width - 1, n)
    v = np.linspace(0, camera.height - 1, n)
    U, V = np.meshgrid(u, v)
    px = np.column_stack([U.ravel(), V.ravel()]).astype(np.float64)
    if camera.has_distortion:
        und = cv2.undistortPoints(
            px.reshape(-1, 1, 2), camera.K, np.asarray(camera.dist, float)
        ).reshape(-1, 2)
    else:
        und = np.column_stack(
            [(px[:, 0] - camera.cx) / camera.fx, (px[:, 1] - camera.cy) / camera.fy]
        )
    rays = np.column_stack([und, np.ones(len(und))]) @ W[:3, :3].T
    c = W[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (road_z - c[2]) / rays[:, 2]
    lam = np.where(np.isfinite(lam) & (lam > 0), lam, np.nan)
    pts = c + lam[:, None] * rays
    return pts[np.all(np.isfinite(pts), axis=1)]


# =========================================================================== rasters


class _ImageCache:
    """A few decoded (and pyramid-reduced) images, shared by the tile threads; tiles are
    visited in drive order."""

    def __init__(self, size: int = 12) -> None:
        self._c: SharedCache[tuple[str, int], np.ndarray | None] = SharedCache(size)

    def get(self, frame: Frame, level: int) -> np.ndarray | None:
        def load() -> np.ndarray | None:
            try:
                img = read_image(frame)
                for _ in range(level):
                    img = cv2.pyrDown(img)
                return img
            except (FrameReadError, OSError) as e:
                log.warning("globalmap: %s not used in the mosaic (%s)", frame.filename, e)
                return None

        return self._c.get((frame.filename, level), load)


def _rasters(
    cfg: MappingConfig,
    drive: Drive,
    traj: Trajectory,
    surf: LocalSurface,
    xyz: np.ndarray,
    resid: np.ndarray,
    prod: MapProducts,
    frames_by_index: dict[int, Frame],
    pair_frames: list[tuple[int, int]] | None = None,
) -> None:
    cam = drive.camera
    ef = traj.export_frame
    crs = ef.crs if ef is not None else LOCAL_CRS
    g2e = GridToEnu(traj.reference, ef.epsg if ef is not None else None)
    # footprints of every posed frame on the local road
    fp_grid: list[np.ndarray] = []
    road_z = np.empty(len(traj))
    cam_xy = traj.positions_enu_m[:, :2]
    zr = surf.height(cam_xy)
    for i in range(len(traj)):
        W = traj.world_from_cam[i]
        road_z[i] = zr[i] if np.isfinite(zr[i]) else W[2, 3] - cam.height_m
        fp = footprint_enu(cam, W, road_z[i])
        fp_grid.append(export_xyz(fp, ef)[:, :2] if len(fp) else np.zeros((0, 2)))
    _check_frame_overlap(cfg, fp_grid, prod)
    samples = [f for f in fp_grid if len(f)]
    pts_grid = export_xyz(xyz, ef)[:, :2] if len(xyz) else np.zeros((0, 2))
    if not samples and not len(pts_grid):
        prod.warnings.append("nothing to rasterise (no footprint, no point)")
        return
    allxy = np.concatenate([*samples, pts_grid]) if samples else pts_grid
    lat, tiles = corridor_tiles(allxy, crs, cfg.gsd_m, cfg.tile_px)
    # footprint bounding boxes in pixel coordinates of the full grid, and frames per tile
    fg = lat.full_grid
    fbox: list[tuple[int, int, int, int] | None] = []
    frames_of_tile: dict[tuple[int, int], list[int]] = {t: [] for t in tiles}
    for i, fp in enumerate(fp_grid):
        if len(fp) < 3:
            fbox.append(None)
            continue
        rc = fg.rowcol_from_xy(fp)
        r0, c0 = np.floor(rc.min(0)).astype(int) - 2
        r1, c1 = np.ceil(rc.max(0)).astype(int) + 2
        fbox.append((r0, r1, c0, c1))
        tp = lat.tile_px
        for tr in range(max(r0 // tp, 0), min(r1 // tp, lat.n_rows - 1) + 1):
            for tc in range(max(c0 // tp, 0), min(c1 // tp, lat.n_cols - 1) + 1):
                if (tr, tc) in frames_of_tile:
                    frames_of_tile[(tr, tc)].append(i)
    # visit tiles in drive order (first frame seeing them) so the image cache hits
    tiles.sort(key=lambda t: (min(frames_of_tile[t]) if frames_of_tile[t] else 1 << 30, t))
    n_full_px = fg.width * fg.height
    write_full = n_full_px <= cfg.max_raster_px
    write_tiles = len(tiles) >= cfg.tiled_vrt_min_tiles or not write_full
    if not write_full:
        msg = (
            f"the corridor's bounding grid has {n_full_px / 1e6:.0f} Mpx (> max_raster_px): "
            "surface.tif/mosaic.tif are not written; use surface.vrt/mosaic.vrt (tiles/)"
        )
        log.warning("globalmap: %s", msg)
        prod.warnings.append(msg)
    prod.grid = {
        "crs": crs,
        "x0_m": fg.x0_m,
        "y0_m": fg.y0_m,
        "gsd_m": fg.gsd_m,
        "width": fg.width,
        "height": fg.height,
        "tile_px": lat.tile_px,
    }
    # pyramid level so that source pixels are about one GSD on the road (anti-aliasing)
    native = (
        float(np.median(traj.world_from_cam[:, 2, 3] - road_z)) / cam.fx if len(traj) else cfg.gsd_m
    )
    level = max(0, int(math.floor(math.log2(max(cfg.gsd_m / max(native, 1e-9), 1.0)))))
    # points per tile (with a margin so interpolation is continuous across tile borders)
    margin = cfg.surface_max_edge_m + _surface_pad_m(cfg)
    # robust per-point height noise (MAD of all residuals; defects are a small minority)
    noise_m = float(1.4826 * np.median(np.abs(resid))) if len(resid) else 0.0
    prod.residual_stats_m["noise_mad_m"] = noise_m
    writers: list[TiledWriter] = []
    try:
        sw = TiledWriter(
            prod.run_dir,
            "surface",
            lat,
            1,
            "float32",
            NODATA_SURFACE,
            write_tiles,
            write_full,
            tags={"units": "m", "description": "height above the local road, negative below"},
        )
        writers.append(sw)
        mw = TiledWriter(prod.run_dir, "mosaic", lat, 3, "uint8", 0, write_tiles, write_full)
        writers.append(mw)
        prev = _Previews(fg, cfg.preview_max_px)
        workers = max(1, int(cfg.raster_workers))
        # each thread works on its own tile, a few frames apart in drive order
        cache = _ImageCache(12 * workers)
        frame_list = [frames_by_index.get(int(k)) for k in traj.frame_indices]
        pf = list(pair_frames or [])

        def two_view(g: GridSpec, resid_g: np.ndarray | None = None) -> np.ndarray:
            return _two_view_mask(cam, traj, surf, g2e, g, pf, fp_grid, road_z, resid_g)

        def compute(t: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            grid = lat.tile_grid(*t)
            sel = _points_in(pts_grid, grid, margin)
            res_t, filled = _surface_tile_filled(
                cfg, pts_grid[sel], resid[sel], grid, noise_m, two_view
            )
            mos_t, wsum = _mosaic_tile(
                cfg,
                cam,
                traj,
                surf,
                g2e,
                grid,
                t,
                lat,
                fbox,
                frames_of_tile[t],
                frame_list,
                res_t,
                road_z,
                cache,
                level,
            )
            res_t[wsum <= 0] = np.nan  # only the imaged corridor
            # filled pixels only where both frames of an ok pair saw the road (with the
            # surface's own heights: a pothole floor near an image border is seen where the road
            # above it would not be). Interpolated ones are kept as before, also across a thin
            # strip seen by one frame between two pairs (a short Delaunay edge bridges it)
            if filled.any():
                res_t[filled & ~two_view(grid, res_t)] = np.nan
            return res_t, mos_t, wsum

        # tiles are computed by worker threads (OpenCV and numpy release the GIL) and written
        # here, in order, a bounded number ahead (GDAL datasets are not shared across threads)
        for t, (res_t, mos_t, wsum) in tqdm(
            zip(tiles, ordered_map(compute, tiles, workers), strict=True),
            total=len(tiles),
            desc="rasters",
            unit="tile",
            leave=False,
        ):
            has_s = bool(np.isfinite(res_t).any())
            has_m = bool((wsum > 0).any())
            if not (has_s or has_m):
                continue
            prod.n_tiles += 1
            prod.surface_px += int(np.isfinite(res_t).sum())
            prod.mosaic_px += int((wsum > 0).sum())
            sw.write(*t, res_t)
            mw.write(*t, mos_t)
            tg = lat.tile_grid(*t)
            info: dict[str, Any] = {
                "row": t[0],
                "col": t[1],
                "bounds": [
                    tg.x0_m,
                    tg.y0_m - tg.height * tg.gsd_m,
                    tg.x0_m + tg.width * tg.gsd_m,
                    tg.y0_m,
                ],
            }
            if write_tiles:
                info["surface"] = f"tiles/surface_{t[0]:04d}_{t[1]:04d}.tif"
                info["mosaic"] = f"tiles/mosaic_{t[0]:04d}_{t[1]:04d}.tif"
            prod.tiles.append(info)
            prev.add(t, lat, res_t, mos_t)
        for w in writers:
            w.close()
    except BaseException:
        for w in writers:
            w.abort()
        raise
    if write_full:
        prod.files["surface"] = "surface.tif"
        prod.files["mosaic"] = "mosaic.tif"
    if write_tiles:
        prod.files["surface_vrt"] = "surface.vrt"
        prod.files["mosaic_vrt"] = "mosaic.vrt"
    prev.write(prod.run_dir)
    prod.files["mosaic_preview"] = "mosaic_preview.png"
    prod.files["surface_preview"] = "surface_preview.png"


def _masked_gauss(r: np.ndarray, m: np.ndarray, sig_px: float) -> np.ndarray:
    num = cv2.GaussianBlur(np.where(m, r, 0).astype(np.float32), (0, 0), sig_px)
    den = cv2.GaussianBlur(m.astype(np.float32), (0, 0), sig_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(m & (den > 1e-3), num / den, np.nan).astype(np.float32)


def _surface_pad_m(cfg: MappingConfig) -> float:
    """Context (m) the surface of a tile needs around it: the coarse smoothing kernel (3σ) and
    the capped fill (its reach plus its kernel), so tile borders stay seamless."""
    fill = max(cfg.surface_fill_max_m, 0.0)
    return max(3 * max(cfg.surface_smooth_flat_m, cfg.surface_smooth_m), 2.5 * fill)


def _surface_tile_filled(
    cfg: MappingConfig,
    xy: np.ndarray,
    resid: np.ndarray,
    grid: GridSpec,
    noise_m: float,
    fill_mask: Callable[[GridSpec], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Residual raster of one tile: Delaunay interpolation of the fused points on a padded grid,
    then masked (normalised) Gaussian smoothing that never spreads values into holes. Where the
    fine (σ = surface_smooth_m) and the coarse (σ = surface_smooth_flat_m) versions agree within
    the point noise and the fine one is within the noise of the road, the coarse one is used
    (flat road: noise averaged); in relief (defect edges and bottoms) a lightly smoothed version
    (σ = surface_smooth_defect_m) keeps the depth, with a soft transition. The padding
    keeps tile borders seamless. With ``fill_mask`` (GridSpec -> (H, W) bool: where the road
    was seen by both frames of an ok pair), pixels within ``surface_fill_max_m`` of the smoothed
    surface, inside that mask, in the strip along its border or in holes no wider than twice
    the cap, and whose fill is road (not relief) are filled (``_fill_region``,
    ``raster.fill_nodata_capped``): the sparse points stop short of the image borders, the
    two-view depth does not. Returns the (H, W) float32
    residual and the (H, W) bool mask of its filled (not interpolated) pixels."""
    # interpolate and smooth on a grid `step` times coarser (the points are ~cm apart and the
    # smoothing is >= 1 cm), then upsample: 4x fewer Delaunay look-ups per tile
    step = max(1, int(cfg.surface_interp_step_px))
    while step > 1 and grid.width % step:
        step -= 1
    g = grid.gsd_m * step
    sig_f = cfg.surface_smooth_m / g
    sig_c = max(cfg.surface_smooth_flat_m / g, sig_f)
    fill_px = max(cfg.surface_fill_max_m, 0.0) / g if fill_mask is not None else 0.0
    pad = int(math.ceil(_surface_pad_m(cfg) / g)) if (sig_c > 0 or fill_px > 0) else 0
    cw, ch = grid.width // step, grid.height // step
    big = GridSpec(
        grid.crs, grid.x0_m - pad * g, grid.y0_m + pad * g, g, cw + 2 * pad, ch + 2 * pad
    )
    r = interpolate_to_grid(xy, resid, big, cfg.surface_max_edge_m, cfg.surface_edge_factor)
    if pad:
        m = np.isfinite(r)
        fine = _masked_gauss(r, m, sig_f) if sig_f > 0 else r
        if sig_c > sig_f and noise_m > 0:
            coarse = _masked_gauss(r, m, sig_c)
            t = cfg.surface_detail_sigmas * noise_m
            # relief = the fine and coarse versions disagree (edges) OR the surface is off the
            # local road (a pothole's smooth bottom: fine ≈ coarse there, but the wide coarse
            # kernel would average its curvature away and lift the bottom)
            w = np.clip((np.abs(fine - coarse) - t) / t, 0.0, 1.0)
            w = np.maximum(w, np.clip((np.abs(fine) - t) / t, 0.0, 1.0))
            sig_d = min(cfg.surface_smooth_defect_m / g, sig_f)
            detail = _masked_gauss(r, m, sig_d) if sig_d > 0.3 else r
            r = np.where(np.isfinite(w), (1 - w) * coarse + w * detail, fine).astype(np.float32)
        else:
            r = fine
    if fill_px > 0 and fill_mask is not None:
        # dilated by one coarse pixel, so the full-resolution clip to the exact two-view mask
        # (after upsampling) is not eaten into by coarse pixels whose centre lies just outside
        seen2 = cv2.dilate(fill_mask(big).astype(np.uint8), np.ones((3, 3), np.uint8))
        allowed = _fill_region(np.isfinite(r), seen2, fill_px)
        # only road is continued: where the nearby measured surface is relief (off the local road
        # by more than the relief threshold), the unseen part of the defect is left as a hole
        lim = max(cfg.surface_detail_sigmas * noise_m, cfg.surface_fill_relief_min_m)
        measured = np.isfinite(r)
        r = fill_nodata_capped(r, allowed, fill_px, max_abs=lim)
        filled = np.isfinite(r) & ~measured
    else:
        filled = np.zeros(r.shape, bool)
    r = r[pad : pad + ch, pad : pad + cw]
    filled = filled[pad : pad + ch, pad : pad + cw]
    if step == 1:
        return r, filled
    m = np.isfinite(r).astype(np.float32)
    size = (grid.width, grid.height)
    num = cv2.resize(np.nan_to_num(r), size, interpolation=cv2.INTER_LINEAR)
    den = cv2.resize(m, size, interpolation=cv2.INTER_LINEAR)
    keep = cv2.resize(m, size, interpolation=cv2.INTER_NEAREST) > 0
    filled = cv2.resize(filled.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(keep & (den > 1e-3), num / den, np.nan).astype(np.float32)
    return out, filled & np.isfinite(out)


def _two_view_mask(
    cam: Camera,
    traj: Trajectory,
    surf: LocalSurface,
    g2e: GridToEnu,
    grid: GridSpec,
    pair_frames: list[tuple[int, int]],
    fp_grid: list[np.ndarray],
    road_z: np.ndarray,
    resid: np.ndarray | None = None,
    margin_m: float = 0.05,
) -> np.ndarray:
    """(H, W) bool: pixels of ``grid`` whose point on the fitted road (plus the (H, W) residual
    height ``resid`` where it is finite) projects inside both
    images (pixel centres 0..width-1, 0..height-1) of at least one of the ``pair_frames`` (pose
    indices), with the fused poses: the part of the corridor where two views give depth.
    ``fp_grid`` holds each frame's footprint samples in the grid CRS (for bounding boxes, widened
    by ``margin_m`` for road relief)."""
    H, W = grid.height, grid.width
    out = np.zeros((H, W), bool)
    boxes: dict[int, tuple[int, int, int, int] | None] = {}

    def box(i: int) -> tuple[int, int, int, int] | None:
        if i not in boxes:
            fp = fp_grid[i]
            b = None
            if len(fp) >= 3:
                rc = grid.rowcol_from_xy(fp)
                m = margin_m / grid.gsd_m
                r0 = max(int(np.floor(rc[:, 0].min() - m)), 0)
                r1 = min(int(np.ceil(rc[:, 0].max() + m)), H - 1)
                c0 = max(int(np.floor(rc[:, 1].min() - m)), 0)
                c1 = min(int(np.ceil(rc[:, 1].max() + m)), W - 1)
                b = (r0, r1, c0, c1) if r1 >= r0 and c1 >= c0 else None
            boxes[i] = b
        return boxes[i]

    todo = []
    for a, b in pair_frames:
        ba, bb = box(a), box(b)
        if ba is None or bb is None:
            continue
        inter = (max(ba[0], bb[0]), min(ba[1], bb[1]), max(ba[2], bb[2]), min(ba[3], bb[3]))
        if inter[1] >= inter[0] and inter[3] >= inter[2]:
            todo.append((a, b, inter))
    if not todo:
        return out
    frames = sorted({i for a, b, _ in todo for i in (a, b)})
    fb = [boxes[i] for i in frames]
    R0, R1 = min(b[0] for b in fb), max(b[1] for b in fb)
    C0, C1 = min(b[2] for b in fb), max(b[3] for b in fb)
    e, n = g2e.pixel_enu(grid, slice(R0, R1 + 1), slice(C0, C1 + 1))
    # the fitted road is smooth on the node scale: evaluate it every ~4 cm and upsample
    st = max(1, int(round(0.04 / grid.gsd_m)))
    zs = surf.height(np.column_stack([e[::st, ::st].ravel(), n[::st, ::st].ravel()]))
    zs = zs.reshape(e[::st, ::st].shape).astype(np.float32)
    z = cv2.resize(zs, (e.shape[1], e.shape[0]), interpolation=cv2.INTER_LINEAR).astype(float)
    if resid is not None:
        rz = resid[R0 : R1 + 1, C0 : C1 + 1]
        z = z + np.where(np.isfinite(rz), rz, 0.0)
    inside: dict[int, np.ndarray] = {}
    for i in frames:
        r0, r1, c0, c1 = boxes[i]
        sl = (slice(r0 - R0, r1 - R0 + 1), slice(c0 - C0, c1 - C0 + 1))
        Wi = traj.world_from_cam[i]
        zz = np.where(np.isfinite(z[sl]), z[sl], road_z[i])
        X = np.stack([e[sl] - Wi[0, 3], n[sl] - Wi[1, 3], zz - Wi[2, 3]], axis=-1)
        u, v = project(cam, X @ Wi[:3, :3])
        with np.errstate(invalid="ignore"):
            inside[i] = (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)
    for a, b, (r0, r1, c0, c1) in todo:
        parts = []
        for i in (a, b):
            ra, _, ca, _ = boxes[i]
            parts.append(inside[i][r0 - ra : r1 - ra + 1, c0 - ca : c1 - ca + 1])
        out[r0 : r1 + 1, c0 : c1 + 1] |= parts[0] & parts[1]
    return out


def _fill_region(valid: np.ndarray, seen2: np.ndarray, fill_px: float) -> np.ndarray:
    """Where the capped fill may act, (H, W) bool, given the measured pixels ``valid`` and the
    two-view mask ``seen2`` (uint8): (1) the strip of width ``fill_px`` along the border of
    the two-view part, where the matches stop short of the image borders; (2) whole holes no
    wider than twice the cap (every pixel within ``fill_px`` of a measured one), the gaps the
    interpolation would bridge with points around. Larger holes inside (dark pothole floors,
    textureless stains) are left entirely: a rim band would creep flat road into them."""
    from scipy import ndimage

    to_edge = cv2.distanceTransform(seen2, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    strip = (seen2 > 0) & (to_edge <= fill_px + 1.0)
    holes = (seen2 > 0) & ~valid
    lab, n = ndimage.label(holes)
    if n == 0:
        return strip
    dist = cv2.distanceTransform((~valid).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    widest = ndimage.maximum(dist, lab, np.arange(1, n + 1))
    small = np.concatenate([[False], np.asarray(widest) <= fill_px])
    return strip | small[lab]


def _points_in(xy: np.ndarray, grid: GridSpec, margin: float) -> np.ndarray:
    x0, y1 = grid.x0_m - margin, grid.y0_m + margin
    x1, y0 = (
        grid.x0_m + grid.width * grid.gsd_m + margin,
        grid.y0_m - grid.height * grid.gsd_m - margin,
    )
    return (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)


def _mosaic_tile(
    cfg: MappingConfig,
    cam: Camera,
    traj: Trajectory,
    surf: LocalSurface,
    g2e: GridToEnu,
    grid: GridSpec,
    t: tuple[int, int],
    lat: Any,
    fbox: list[tuple[int, int, int, int] | None],
    frame_ids: list[int],
    frame_list: list[Frame | None],
    res_t: np.ndarray,
    road_z: np.ndarray,
    cache: _ImageCache,
    level: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Project the frames seeing tile t onto the fitted road (+ residual) and blend them with
    feathered weights. Returns (H, W, 3) uint8 (0 = nodata) and the weight sum (H, W)."""
    tp = lat.tile_px
    acc = np.zeros((tp, tp, 3), np.float32)
    wsum = np.zeros((tp, tp), np.float32)
    if not frame_ids:
        return acc.astype(np.uint8), wsum
    # union of the footprint windows inside this tile
    boxes = []
    for i in frame_ids:
        b = fbox[i]
        r0, r1 = max(b[0] - t[0] * tp, 0), min(b[1] - t[0] * tp, tp - 1)
        c0, c1 = max(b[2] - t[1] * tp, 0), min(b[3] - t[1] * tp, tp - 1)
        boxes.append((r0, r1, c0, c1) if r1 >= r0 and c1 >= c0 else None)
    valid = [b for b in boxes if b is not None]
    if not valid:
        return acc.astype(np.uint8), wsum
    R0, R1 = min(b[0] for b in valid), max(b[1] for b in valid)
    C0, C1 = min(b[2] for b in valid), max(b[3] for b in valid)
    e, n = g2e.pixel_enu(grid, slice(R0, R1 + 1), slice(C0, C1 + 1))
    # the fitted road is smooth on the node scale (25 cm): evaluate it every 8 px and upsample
    zs = surf.height(np.column_stack([e[::8, ::8].ravel(), n[::8, ::8].ravel()]))
    zs = zs.reshape(e[::8, ::8].shape).astype(np.float32)
    if np.isfinite(zs).any():
        zs = np.where(np.isfinite(zs), zs, np.nanmedian(zs))
    z = cv2.resize(zs, (e.shape[1], e.shape[0]), interpolation=cv2.INTER_LINEAR).astype(float)
    rz = res_t[R0 : R1 + 1, C0 : C1 + 1]
    z = z + np.where(np.isfinite(rz), rz, 0.0)
    scale = 0.5**level
    border = cfg.mosaic_border_px
    feather = max(cfg.feather_px, 1)
    for i, b in zip(frame_ids, boxes, strict=True):
        fr = frame_list[i]
        if b is None or fr is None:
            continue
        img = cache.get(fr, level)
        if img is None:
            continue
        r0, r1, c0, c1 = b
        sl = (slice(r0 - R0, r1 - R0 + 1), slice(c0 - C0, c1 - C0 + 1))
        zz = z[sl]
        zz = np.where(np.isfinite(zz), zz, road_z[i])
        W = traj.world_from_cam[i]
        X = np.stack([e[sl] - W[0, 3], n[sl] - W[1, 3], zz - W[2, 3]], axis=-1)
        Xc = X @ W[:3, :3]  # R^T (X - c), row-vector form
        u, v = project(cam, Xc)
        d = np.minimum.reduce(
            [u - border, cam.width - 1 - border - u, v - border, cam.height - 1 - border - v]
        )
        w = np.clip(d / feather, 0.0, 1.0)
        w = np.where(np.isfinite(w), w, 0.0).astype(np.float32) ** 2
        if not (w > 0).any():
            continue
        # pixel centre convention: full-res (u, v) -> level-l ((u + 0.5) * s - 0.5)
        mx = ((np.nan_to_num(u, nan=-1e4) + 0.5) * scale - 0.5).astype(np.float32)
        my = ((np.nan_to_num(v, nan=-1e4) + 0.5) * scale - 0.5).astype(np.float32)
        # replicate: with mosaic_border_px = 0 the outermost half pixel must not blend in black
        samp = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        tile_sl = (slice(r0, r1 + 1), slice(c0, c1 + 1))
        acc[tile_sl] += samp.astype(np.float32) * w[..., None]
        wsum[tile_sl] += w
    out = np.zeros((tp, tp, 3), np.uint8)
    has = wsum > 0
    out[has] = np.clip(np.round(acc[has] / wsum[has, None]), 1, 255).astype(np.uint8)
    return out, wsum


class _Previews:
    """Downsampled mosaic and colour-mapped surface over the whole corridor (bounded size)."""

    def __init__(self, fg: GridSpec, max_px: int) -> None:
        self.f = max(1, int(math.ceil(max(fg.width, fg.height) / max_px)))
        self.h = max(1, fg.height // self.f)
        self.w = max(1, fg.width // self.f)
        self.mos = np.zeros((self.h, self.w, 3), np.uint8)
        self.res = np.full((self.h, self.w), np.nan, np.float32)

    def add(self, t: tuple[int, int], lat: Any, res_t: np.ndarray, mos_t: np.ndarray) -> None:
        tp, f = lat.tile_px, self.f
        # exact integer bounds so neighbouring tiles meet without a gap
        r0, c0 = t[0] * tp // f, t[1] * tp // f
        sh, sw = (t[0] + 1) * tp // f - r0, (t[1] + 1) * tp // f - c0
        hh, ww = min(sh, self.h - r0), min(sw, self.w - c0)
        if hh <= 0 or ww <= 0:
            return
        m = cv2.resize(mos_t, (sw, sh), interpolation=cv2.INTER_AREA)
        valid = np.isfinite(res_t).astype(np.float32)
        num = cv2.resize(np.nan_to_num(res_t), (sw, sh), interpolation=cv2.INTER_AREA)
        den = cv2.resize(valid, (sw, sh), interpolation=cv2.INTER_AREA)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(den > 0.25, num / den, np.nan)
        mm = m[:hh, :ww]
        has = mm.any(axis=2)
        self.mos[r0 : r0 + hh, c0 : c0 + ww][has] = mm[has]
        rr = r[:hh, :ww]
        fin = np.isfinite(rr)
        self.res[r0 : r0 + hh, c0 : c0 + ww][fin] = rr[fin]

    def write(self, run_dir: Path) -> None:
        from matplotlib import colormaps

        with atomic_path(run_dir / "mosaic_preview.png") as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(self.mos, cv2.COLOR_RGB2BGR))
        fin = np.isfinite(self.res)
        lim = 0.005
        if fin.any():
            lim = max(lim, float(np.percentile(np.abs(self.res[fin]), 99.5)))
        rgba = colormaps["RdBu"](np.clip(np.nan_to_num(self.res) / (2 * lim) + 0.5, 0, 1))
        img = (rgba[..., :3] * 255).astype(np.uint8)
        img[~fin] = 235
        label = f"residual height: red {-lim * 1000:.0f} mm (below) .. blue +{lim * 1000:.0f} mm"
        pad = np.full((28, img.shape[1], 3), 255, np.uint8)
        cv2.putText(pad, label, (4, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        out = np.vstack([img, pad]) if img.shape[1] >= 200 else img
        with atomic_path(run_dir / "surface_preview.png") as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(out, cv2.COLOR_RGB2BGR))
