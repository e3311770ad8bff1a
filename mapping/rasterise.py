"""The global map's rasters, tile by tile: the frames' road footprints give the tiles of a
global lattice that the corridor passes; each tile's residual surface and mosaic are computed by
worker threads and written in order (per-tile files + VRTs, and/or window by window into
``surface.tif``/``mosaic.tif``), with the previews."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.core.memory import release_free_memory
from roadsurf.core.parallel import ordered_map
from roadsurf.io import runfolder as rf
from roadsurf.io.drive import Drive, Frame
from roadsurf.io.formats import LOCAL_FRAME_TEXT, GridSpec
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.datum import RESIDUAL_DATUM, vertical_datum
from roadsurf.mapping.dense_cloud import DenseCloudWriter, cloud_stride
from roadsurf.mapping.dense_fuse import (
    NOBS,
    SIGMA,
    DenseSurface,
    dense_gsd_m,
    dense_px_m,
    surface_height_grid,
)
from roadsurf.mapping.dense_seams import DENSE_SEAMS, SeamSamples, seam_stride_cells
from roadsurf.mapping.export import export_xyz
from roadsurf.mapping.mosaic import ImageCache, mosaic_tile
from roadsurf.mapping.overlap import check_frame_overlap
from roadsurf.mapping.previews import Previews
from roadsurf.mapping.raster import (
    LOCAL_CRS,
    GridToEnu,
    TiledWriter,
    corridor_tiles,
    fill_nodata_capped,
)
from roadsurf.mapping.rasterfill import fill_inward, single_view_heights
from roadsurf.mapping.surface import LocalSurface
from roadsurf.mapping.surface_raster import (
    points_in,
    surface_pad_m,
    surface_tile_filled,
    two_view_mask,
)
from roadsurf.mapping.types import MapProducts, Trajectory

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

NODATA_SURFACE = float("nan")


def rasterise(
    cfg: MappingConfig,
    drive: Drive,
    traj: Trajectory,
    surf: LocalSurface,
    xyz: np.ndarray,
    resid: np.ndarray,
    prod: MapProducts,
    frames_by_index: dict[int, Frame],
    pair_frames: list[tuple[int, int]] | None = None,
    pairs: list[PairResult] | None = None,
) -> None:
    """Write the surface and mosaic rasters (and previews) of the corridor into
    ``prod.run_dir``, recording files, tiles, pixel counts and warnings in ``prod``.
    ``pair_frames``: pose indices of the ok pairs (the capped fill acts where both saw the road).
    With ``cfg.surface_source == "dense"`` the surface is the dense one fused from ``pairs``
    (``mapping.dense_fuse``), on the dense GSD, with its count and σ rasters."""
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
        fp = cam.footprint_grid_enu(W, road_z[i])
        fp_grid.append(export_xyz(fp, ef)[:, :2] if len(fp) else np.zeros((0, 2)))
    check_frame_overlap(cfg, fp_grid, prod)
    samples = [f for f in fp_grid if len(f)]
    pts_grid = export_xyz(xyz, ef)[:, :2] if len(xyz) else np.zeros((0, 2))
    if not samples and not len(pts_grid):
        prod.warnings.append("nothing to rasterise (no footprint, no point)")
        return
    allxy = np.concatenate([*samples, pts_grid]) if samples else pts_grid
    dense = cfg.surface_source == "dense" and pairs is not None
    gsd = dense_gsd_m(cfg, cam, traj, road_z) if dense else cfg.gsd_m
    if dense and cfg.dense_gsd_m == 0 and cfg.gsd_m > gsd and cfg.gsd_m != MappingConfig.gsd_m:
        msg = (
            f"mapping.gsd_m = {cfg.gsd_m:g} m sets the sparse surface's cell; the dense surface "
            f"(surface_source: dense, the default) is rastered at {gsd:g} m from the images. "
            f"For {cfg.gsd_m:g} m cells set mapping.dense_gsd_m: {cfg.gsd_m:g}"
        )
        log.warning("globalmap: %s", msg)
        prod.warnings.append(msg)
    # without GPS the rasters carry no CRS: every one says what its metres are
    frame_tags = {"COORDINATES": LOCAL_FRAME_TEXT} if ef is None else {}
    tags = {
        "units": "m",
        "description": "height above the local road, negative below",
        "VERTICAL_DATUM": RESIDUAL_DATUM,
        "ROAD_HEIGHT_DATUM": vertical_datum(cfg, drive, traj.reference is not None),
        **frame_tags,
    }
    if dense:  # the matching window's ground footprint: what the raster resolves (detection)
        tags["DENSE_FOOTPRINT_M"] = (
            f"{cfg.dense.window_px * dense_px_m(cfg, cam, traj, road_z):.6f}"
        )
        # the deepest search below the road plane (a pair whose floor reaches the first one
        # over a patch is matched again down to it): a cell at it may be deeper
        deepest = cfg.dense.deepest_search_m(cam.height_m)
        tags["DENSE_SEARCH_DEPTH_M"] = f"{deepest:.6f}"
    lat, tiles = corridor_tiles(allxy, crs, gsd, cfg.tile_px)
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
    native = float(np.median(traj.world_from_cam[:, 2, 3] - road_z)) / cam.fx if len(traj) else gsd
    level = max(0, int(math.floor(math.log2(max(gsd / max(native, 1e-9), 1.0)))))
    # points per tile (with a margin so interpolation is continuous across tile borders)
    margin = cfg.surface_max_edge_m + surface_pad_m(cfg)
    # robust per-point height noise (MAD of all residuals; defects are a small minority)
    noise_m = float(MAD_TO_SIGMA * np.median(np.abs(resid))) if len(resid) else 0.0
    prod.residual_stats_m["noise_mad_m"] = noise_m
    writers: list[TiledWriter] = []
    try:
        sw = TiledWriter(
            prod.run_dir,
            rf.SURFACE,
            lat,
            1,
            "float32",
            NODATA_SURFACE,
            write_tiles,
            write_full,
            tags=tags,
        )
        writers.append(sw)
        mw = TiledWriter(
            prod.run_dir, rf.MOSAIC, lat, 3, "uint8", 0, write_tiles, write_full, frame_tags
        )
        writers.append(mw)
        prev = Previews(fg, cfg.preview_max_px)
        workers = max(1, int(cfg.raster_workers))
        ds = None
        cloud: DenseCloudWriter | None = None
        if dense:
            ds = DenseSurface(
                cfg, drive, pairs or [], traj, surf, g2e, lat, tiles, fp_grid, workers
            )
            cell_px = gsd / dense_px_m(cfg, cam, traj, road_z)  # work-grid px per cell
            ds.seams = SeamSamples(fg, seam_stride_cells(cfg.dense.window_px, cell_px))
            # cloud.ply becomes the dense cloud (the sparse one written before is replaced)
            datum = vertical_datum(cfg, drive, ef is not None)
            cloud = DenseCloudWriter(
                prod.run_dir / rf.CLOUD_PLY,
                [
                    f"crs: {ef.crs if ef is not None else LOCAL_FRAME_TEXT}",
                    f"residual_m: {RESIDUAL_DATUM}",
                    f"vertical_datum: {datum}",
                ],
            )
            stride = cloud_stride(gsd, cfg.dense_cloud_spacing_m)
            alt0 = float(ef.ref.alt_m) if ef is not None else 0.0
            nobs_tags = {"description": "pairs observing the cell (dense surface)", **frame_tags}
            nw = TiledWriter(
                prod.run_dir, NOBS, lat, 1, "uint8", 0, write_tiles, write_full, nobs_tags
            )
            writers.append(nw)
            sigma_tags = {
                "units": "m",
                "description": "standard deviation of the cell's fused height",
                **frame_tags,
            }
            gw = TiledWriter(
                prod.run_dir,
                SIGMA,
                lat,
                1,
                "float32",
                NODATA_SURFACE,
                write_tiles,
                write_full,
                sigma_tags,
            )
            writers.append(gw)
        # each thread works on its own tile, a few frames apart in drive order
        cache = ImageCache(12 * workers)
        frame_list = [frames_by_index.get(int(k)) for k in traj.frame_indices]
        pf = list(pair_frames or [])
        single_view = ds is not None and cfg.dense_single_view == "road"
        # the modelled cells' σ: the road's spread about the local road model, read on the
        # feature points (their MAD also holds their matching noise: an upper bound)
        model_sigma = np.float32(noise_m)
        near_px = cfg.dense_single_view_relief_m / gsd

        def two_view(g: GridSpec, resid_g: np.ndarray | None = None) -> np.ndarray:
            return two_view_mask(cam, traj, surf, g2e, g, pf, fp_grid, road_z, resid_g)

        def compute(t: tuple[int, int]) -> tuple[np.ndarray, ...]:
            grid = lat.tile_grid(*t)
            nobs_t = sig_t = None
            if ds is not None:
                dt = ds.tile(t)
                res_t, nobs_t, sig_t = dt.residual_m, dt.n_obs, dt.sigma_m
                filled = np.zeros(res_t.shape, bool)
                # the relief a fill may bridge: more is a step (a pothole wall)
                lim = max(cfg.surface_detail_sigmas * noise_m, cfg.surface_fill_relief_min_m)
                if cfg.dense.hole_fill_m > 0 and np.isfinite(res_t).any():
                    # holes the matching leaves inside the measured surface (occluded or
                    # smeared pothole walls) from the dense heights around them, before the
                    # sparse surface (its interpolation reads pothole floors shallow)
                    out, near = fill_inward(res_t, cfg.dense.hole_fill_m / grid.gsd_m, lim)
                    filled = np.isfinite(out) & ~np.isfinite(res_t)
                    res_t = out
                else:
                    near = np.isfinite(res_t)
                if cfg.dense_sparse_fill and not np.isfinite(res_t).all():
                    sel = points_in(pts_grid, grid, margin)
                    if sel.sum() >= 3:
                        res_s, _ = surface_tile_filled(
                            cfg, pts_grid[sel], resid[sel], grid, noise_m, None
                        )
                        take = ~np.isfinite(res_t) & np.isfinite(res_s) & ~near
                        res_t = np.where(take, res_s, res_t).astype(np.float32)
                if cfg.dense_fill_max_m > 0 and np.isfinite(res_t).any():
                    # the matching windows stop a few px short of the two-view part's border
                    out = fill_nodata_capped(
                        res_t, two_view(grid, res_t), cfg.dense_fill_max_m / grid.gsd_m, lim
                    )
                    filled |= np.isfinite(out) & ~np.isfinite(res_t)
                    res_t = out
            else:
                sel = points_in(pts_grid, grid, margin)
                res_t, filled = surface_tile_filled(
                    cfg, pts_grid[sel], resid[sel], grid, noise_m, two_view
                )
            mos_t, wsum = mosaic_tile(
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
            tv = two_view(grid, res_t) if filled.any() or single_view else None
            if filled.any() and tv is not None:
                res_t[filled & ~tv] = np.nan
            pts = None
            n_model = 0
            if nobs_t is not None and sig_t is not None:
                gone = ~np.isfinite(res_t)
                n_all = nobs_t
                nobs_t = np.where(gone, 0, np.minimum(nobs_t, 255)).astype(np.uint8)
                sig_t = np.where(gone, np.nan, sig_t).astype(np.float32)
                if single_view and tv is not None:
                    # imaged by one frame only: no parallax, the road model (count 0)
                    model = gone & (wsum > 0) & ~tv
                    if model.any():
                        res_t[model] = single_view_heights(res_t, model, near_px, lim)
                        model &= np.isfinite(res_t)
                        sig_t[model] = model_sigma
                    n_model = int(model.sum())
                pts = cloud_points(grid, res_t, n_all, mos_t)
            return res_t, mos_t, wsum, nobs_t, sig_t, pts, n_model

        def cloud_points(
            grid: GridSpec, res_t: np.ndarray, n_t: np.ndarray, mos_t: np.ndarray
        ) -> tuple[np.ndarray, ...] | None:
            """The measured cells of a dense tile (every ``stride``-th row and column) as
            points: export xyz, colour, residual, count (the module docstring of dense_cloud)."""
            keep = np.isfinite(res_t) & (n_t > 0)
            if stride > 1:
                keep[np.arange(grid.height) % stride != 0] = False
                keep[:, np.arange(grid.width) % stride != 0] = False
            if not keep.any():
                return None
            e, n = g2e.pixel_enu(grid, slice(0, grid.height), slice(0, grid.width))
            z = surface_height_grid(surf, e, n, grid.gsd_m) + res_t
            keep &= np.isfinite(z)
            rr, cc = np.nonzero(keep)
            x = grid.x0_m + (cc + 0.5) * grid.gsd_m
            y = grid.y0_m - (rr + 0.5) * grid.gsd_m
            if ef is None:  # local ENU: the grid is ENU itself
                x, y = e[rr, cc], n[rr, cc]
                h = z[rr, cc]
            else:  # ellipsoidal, as ExportFrame.utm_from_enu writes the sparse cloud
                h = z[rr, cc] + alt0 + g2e.height_lift(grid, x, y)
            xyz = np.column_stack([x, y, h])
            return xyz, mos_t[rr, cc], res_t[rr, cc], n_t[rr, cc]

        # tiles are computed by worker threads (OpenCV and numpy release the GIL) and written
        # here, in order, a bounded number ahead (GDAL datasets are not shared across threads)
        for t, (res_t, mos_t, wsum, nobs_t, sig_t, pts, n_model) in tqdm(
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
            prod.surface_model_px += n_model
            prod.mosaic_px += int((wsum > 0).sum())
            sw.write(*t, res_t)
            mw.write(*t, mos_t)
            if ds is not None:
                nw.write(*t, nobs_t)
                gw.write(*t, sig_t)
            if cloud is not None and pts is not None:
                cloud.add(*pts)
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
                info["surface"] = f"{rf.TILES_DIR}/{rf.tile_filename(rf.SURFACE, *t)}"
                info["mosaic"] = f"{rf.TILES_DIR}/{rf.tile_filename(rf.MOSAIC, *t)}"
            prod.tiles.append(info)
            prev.add(t, lat, res_t, mos_t)
            del res_t, mos_t, wsum, nobs_t, sig_t, pts
            # the tile's freed arrays back to the system (glibc keeps freed pages resident
            # in its arenas): a 3,000-frame map stage peaked at 892 MB, 845 MB with it
            release_free_memory()
        for w in writers:
            w.close()
        if cloud is not None:
            cloud.close()
            area = (prod.surface_px - prod.surface_model_px) * gsd * gsd
            prod.residual_stats_m["dense_cloud_points"] = cloud.n
            prod.residual_stats_m["dense_cloud_points_per_m2"] = cloud.n / area if area else 0.0
    except BaseException:
        for w in writers:
            w.abort()
        if cloud is not None:
            cloud.abort()
        raise
    if write_full:
        prod.files["surface"] = rf.SURFACE_TIF
        prod.files["mosaic"] = rf.MOSAIC_TIF
    if write_tiles:
        prod.files["surface_vrt"] = rf.SURFACE_VRT
        prod.files["mosaic_vrt"] = rf.MOSAIC_VRT
    if ds is None:  # a sparse map: an earlier dense run's seam samples would outrank its own
        (prod.run_dir / DENSE_SEAMS).unlink(missing_ok=True)
    else:
        for name in (NOBS, SIGMA):
            if write_full:
                prod.files[name] = f"{name}.tif"
            if write_tiles:
                prod.files[f"{name}_vrt"] = f"{name}.vrt"
        if ds.seams is not None:  # the pairs' samples where they overlap (evaluate's seams)
            ds.seams.write(prod.run_dir / DENSE_SEAMS)
            prod.files["dense_seams"] = DENSE_SEAMS
        else:  # an earlier dense run's samples would outrank this run's sparse points
            (prod.run_dir / DENSE_SEAMS).unlink(missing_ok=True)
        st = ds.stats
        prod.timings_s["dense_match"] = round(st["match_s"], 3)
        prod.residual_stats_m["dense_pairs"] = st["pairs"]
        prod.residual_stats_m["dense_valid_px"] = st["valid_px"]
        if st["pairs_failed"]:
            msg = f"dense surface: {st['pairs_failed']} of {st['pairs']} pairs not matched"
            log.warning("globalmap: %s", msg)
            prod.warnings.append(msg)
    _remove_stale_rasters(prod, {rel for w in writers for _, _, rel in w.tile_files})
    if prod.surface_model_px:
        log.info(
            "globalmap: %d of %d surface cells (%.0f %%) seen by one frame only: the road model "
            "(count 0 in %s)",
            prod.surface_model_px,
            prod.surface_px,
            100.0 * prod.surface_model_px / max(prod.surface_px, 1),
            NOBS,
        )
    prev.write(prod.run_dir)
    prod.files["mosaic_preview"] = rf.MOSAIC_PREVIEW
    prod.files["surface_preview"] = rf.SURFACE_PREVIEW


def _remove_stale_rasters(prod: MapProducts, tiles_written: set[str]) -> None:
    """Remove the rasters an earlier run of this folder left that this one did not write (a
    dense run's surface_nobs / surface_sigma after a switch to the sparse surface, tiles of an
    older grid): beside this run's files they would be read as its own."""
    wrote = set(prod.files.values())
    for stem in (rf.SURFACE, rf.MOSAIC, NOBS, SIGMA):
        for ext in (".tif", ".vrt"):
            if f"{stem}{ext}" not in wrote:
                (prod.run_dir / f"{stem}{ext}").unlink(missing_ok=True)
    tiles = prod.run_dir / rf.TILES_DIR
    if tiles.is_dir():
        for p in tiles.glob("*.tif"):
            if f"{rf.TILES_DIR}/{p.name}" not in tiles_written:
                p.unlink(missing_ok=True)
