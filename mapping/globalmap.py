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
   With ``surface_source = "dense"`` the residual surface is instead every pixel of each ok
   pair's overlap, matched densely and fused per cell (``mapping.dense_fuse``), on the images'
   ground sampling, with ``surface_nobs``/``surface_sigma`` rasters beside it.
5. ``cloud.ply`` (export CRS), ``map_points.npz`` (ENU, for detection), PNG previews.

This module is the stage (``run``, ``build_map``); steps 1-2 are in ``mapping.cloud``, step 4 in
``mapping.rasterise`` (with ``overlap``, ``surface_raster``, ``mosaic`` and ``previews``).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.atomic import (
    UNREADABLE,
    read_json_object,
    write_json_atomic,
    write_npz_atomic,
)
from roadsurf.core.config import to_dict
from roadsurf.core.fingerprint import Fingerprint
from roadsurf.core.fits import robust_sigma
from roadsurf.core.geometry import utm_exception_key
from roadsurf.io import runfolder as rf
from roadsurf.io.drive import Drive
from roadsurf.io.runfolder import RunFolder, read_fingerprint
from roadsurf.mapping.cloud import align_patches, collect_points, voxel_fuse
from roadsurf.mapping.config import DENSE_SURFACE_FIELDS, NOT_IN_FINGERPRINT, MappingConfig
from roadsurf.mapping.datum import vertical_datum
from roadsurf.mapping.export import write_cloud_ply
from roadsurf.mapping.raster import bounded_block_cache
from roadsurf.mapping.rasterise import rasterise
from roadsurf.mapping.surface import LocalSurface
from roadsurf.mapping.types import MapProducts, Trajectory

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

# =========================================================================== entry point


def run(
    cfg: MappingConfig, drive: Drive, pairs: list[PairResult], traj: Trajectory, run_dir: str | Path
) -> MapProducts:
    """Build and write the global map products into ``run_dir`` (resumes when unchanged)."""
    run_dir = Path(run_dir)
    key = _fingerprint(cfg, pairs, traj, drive, run_dir)
    rep_path = run_dir / rf.MAP_REPORT
    if not cfg.overwrite and rep_path.is_file():
        try:
            rep = read_json_object(rep_path)
            if rep.get("fingerprint") == key:
                changed = _changed_files(run_dir, rep)
                if not changed:
                    log.info("globalmap: inputs unchanged, reusing the map in %s", run_dir)
                    return MapProducts.from_report(rep)
                log.warning(
                    "globalmap: %s missing or changed since the map was built; rebuilding", changed
                )
        except UNREADABLE as e:
            log.warning("globalmap: cached report unreadable (%s); rebuilding", e)
    # the record goes first: a run stopped while rewriting the map leaves no record of the old
    # map beside new files (a resume would trust a sparse cloud or rasters on two grids)
    rep_path.unlink(missing_ok=True)
    prod = build_map(cfg, drive, pairs, traj, run_dir)
    rep = {"fingerprint": key, **prod.to_report()}
    rep["file_bytes"] = {
        f: (run_dir / f).stat().st_size for f in _map_files(rep) if (run_dir / f).is_file()
    }
    write_json_atomic(rep_path, rep)
    return prod


def _map_files(rep: dict) -> list[str]:
    """The map's files a report names (run-folder paths): ``files`` and every tile's."""
    tiles = [v for t in rep.get("tiles", []) for v in t.values() if isinstance(v, str)]
    return [*rep.get("files", {}).values(), *tiles]


def _changed_files(run_dir: Path, rep: dict) -> str:
    """The map's files (``_map_files``) that are missing, or whose size differs from the one
    recorded (``file_bytes``; a truncated raster or tile), as text; "" when none."""
    sizes = rep.get("file_bytes") or {}
    bad = []
    for f in _map_files(rep):
        p = run_dir / f
        if not p.exists() or (f in sizes and p.is_file() and p.stat().st_size != sizes[f]):
            bad.append(str(f))
    return ", ".join(bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")


def _fingerprint(
    cfg: MappingConfig,
    pairs: list[PairResult],
    traj: Trajectory,
    drive: Drive | None = None,
    run_dir: Path | None = None,
) -> str:
    """What the map depends on (a fixed byte stream): the config, the poses, every pair's status
    and content (its points and pixels, and the reconstruction's fingerprint of the pair's
    settings, camera and image files when ``run_dir`` holds one), the camera, the vertical
    datum of the exported heights and, for a rolling shutter, the dense resampling's version."""
    fp = Fingerprint()
    d = to_dict(cfg)
    fp.add_json({k: v for k, v in d.items() if k not in NOT_IN_FINGERPRINT})
    if cfg.surface_source != "sparse":  # the matching's device and threads change no result
        dense = {k: d[k] for k in DENSE_SURFACE_FIELDS}
        dense["dense"] = {k: v for k, v in d["dense"].items() if k not in ("device", "cpu_threads")}
        fp.add_json(dense)
        from roadsurf.mapping.dense_cells import DENSE_SURFACE_VERSION

        fp.add_text(f"dense_surface:{DENSE_SURFACE_VERSION}")  # the code, not only its settings
    fp.add_array(traj.world_from_cam)
    ref = traj.reference
    if ref is not None and (utm := utm_exception_key(ref.lat_deg, ref.lon_deg)):
        fp.add_text(utm)  # the grid's CRS
    run = RunFolder(run_dir) if run_dir is not None else None
    for p in pairs:
        fp.add_text(f"{p.index_a},{p.index_b},{p.status},{p.n_points}")
        fp.add_array(p.points_cam_a_m).add_array(p.px_a)
        if run is not None:
            fp.add_text(read_fingerprint(run.pair(p.index_a, p.index_b)) or "-")
    if drive is not None:
        fp.add_json(drive.camera.fingerprint_fields()).add_text(vertical_datum(cfg, drive))
        if cfg.surface_source != "sparse" and drive.camera.readout_s > 0:
            from roadsurf.reconstruction.dense.rolling import DENSE_ROLLING_VERSION

            fp.add_text(f"dense_rolling:{DENSE_ROLLING_VERSION}")  # how the rows are resampled
    return fp.hexdigest(16)


# =========================================================================== building


def build_map(
    cfg: MappingConfig, drive: Drive, pairs: list[PairResult], traj: Trajectory, run_dir: Path
) -> MapProducts:
    t0 = time.perf_counter()
    run_dir.mkdir(parents=True, exist_ok=True)
    ef = traj.export_frame
    crs = ef.crs if ef is not None else None
    prod = MapProducts(run_dir=run_dir, crs=crs, gsd_m=cfg.gsd_m)
    frames_by_index = {f.index: f for f in drive.frames}
    pose_of = {fn: i for i, fn in enumerate(traj.filenames)}

    # ---------------------------------------------------------------- 1-2 points, fused
    xyz, rgb, frame_idx, n_raw = collect_points(cfg, drive, pairs, traj, frames_by_index, pose_of)
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
            "mad": robust_sigma(resid),  # all finite: the same as the plain 1.4826 MAD
        }

    # ---------------------------------------------------------------- 5 point products
    t2 = time.perf_counter()
    write_npz_atomic(
        run_dir / rf.MAP_POINTS,
        xyz=xyz,
        rgb=rgb,
        residual_m=resid.astype(np.float32),
        frame_index=frame_idx,
        n_obs=nobs,
    )
    prod.files["map_points"] = rf.MAP_POINTS
    datum = vertical_datum(cfg, drive, ef is not None)
    write_cloud_ply(
        run_dir / rf.CLOUD_PLY,
        xyz,
        rgb,
        resid,
        ef,
        extra={"n_obs": nobs.astype(np.int32)},
        vertical_datum=datum,
    )
    prod.files["cloud"] = rf.CLOUD_PLY
    prod.timings_s["cloud"] = round(time.perf_counter() - t2, 3)

    # ---------------------------------------------------------------- 4 rasters
    t3 = time.perf_counter()
    # pose indices of the ok pairs: the surface exists only where both frames of one saw the road
    pair_frames = [
        (pose_of[p.frame_a], pose_of[p.frame_b])
        for p in pairs
        if p.ok and p.n_points > 0 and p.frame_a in pose_of and p.frame_b in pose_of
    ]
    with bounded_block_cache():  # memory flat in the drive's length
        rasterise(cfg, drive, traj, surf, xyz, resid, prod, frames_by_index, pair_frames, pairs)
    if prod.grid:  # the dense surface has its own GSD
        prod.gsd_m = float(prod.grid["gsd_m"])
    prod.timings_s["rasters"] = round(time.perf_counter() - t3, 3)
    prod.timings_s["total"] = round(time.perf_counter() - t0, 3)
    return prod
