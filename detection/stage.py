"""Detection stage entry point: per-pair 3D segmentation, global-map defects, GIS outputs.

``run(cfg, drive, pairs, traj, run_dir, *, frame_probs=None, fusion=None)`` returns a
``DetectionResult`` and writes RUN/defects.geojson, RUN/defects.csv, RUN/frames.csv and
RUN/detection.json (provenance and resume state). See docs/detection.md.

Steps:
1. per pair: recursive plane fit (eq. 4.8-4.10) and CORRECT_DEFECTS (Fig. 4.3) -> refined
   defect points, placed in the map with the trajectory;
2. on the map: the residual surface raster (RUN/surface.tif, else rasterised points) is segmented
   by hysteresis thresholds relative to its measured noise, seeds and refined points are clustered
   with flat-kernel mean shift (eq. 5.11-5.12), and each defect is vetted by its 3D evidence and
   measured;
3. frame labels and 2D masks: each defect's map cells projected into every frame of an ok pair
   (every posed frame with GPS) through its pose; the deep defect area inside the image labels
   the frame (the simulator's rule), fused with CNN probabilities when ``frame_probs`` is
   given; a frame's mask shows the defects it sees, and each defect lists those frames
   (``framemasks``: frames.csv, RUN/masks/ and the defects agree).

This module only sequences the steps. Step 1: ``pairs`` (and ``planefit``, ``refine``,
``cracks``); the map's inputs: ``mapinputs``; step 2: ``windows`` + ``mapseg`` (segmentation),
``ruts`` (traced ruts), ``measurement`` (vetting, depths; ``dense`` for the dense reading),
``crackmap`` (cracks pooled over pairs); step 3: ``framemasks``, ``framelabels``; files:
``output``.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.config import to_dict
from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.crackmap import crack_defects
from roadsurf.detection.dense import DenseContext
from roadsurf.detection.framelabels import frame_labels, fuse_labels, pair_frame_scores
from roadsurf.detection.framemasks import (
    DefectCells,
    FrameView,
    frame_views,
    outline_cells,
    road_planes,
    write_frame_masks,
)
from roadsurf.detection.mapinputs import (
    depth_points,
    evidence_points,
    frame_footprints,
    load_surface,
    mapped_area,
    pair_keys,
    pair_points,
)
from roadsurf.detection.measurement import measure_regions, renumber
from roadsurf.detection.output import load_result, signature, write_outputs
from roadsurf.detection.pairs import analyse_pairs
from roadsurf.detection.rasterseeds import raster_seeds
from roadsurf.detection.ruts import trace_ruts
from roadsurf.detection.rutscan import scan_seeds
from roadsurf.detection.types import Defect, DetectionResult
from roadsurf.detection.windows import PointsSource, RasterSource, segment_windows
from roadsurf.io.drive import Drive
from roadsurf.io.runfolder import DETECTION_JSON, RunFolder
from roadsurf.mapping.raster import bounded_block_cache
from roadsurf.mapping.types import Trajectory
from roadsurf.reconstruction.types import PairResult

if TYPE_CHECKING:
    from roadsurf.detection.classifier.fusion import FusionRule

log = logging.getLogger(__name__)


def run(
    cfg: DetectionConfig,
    drive: Drive,
    pairs: list[PairResult],
    traj: Trajectory,
    run_dir: Path,
    *,
    frame_probs: dict[str, float] | None = None,
    fusion: FusionRule | None = None,
) -> DetectionResult:
    """Detect and measure defects; write the output files into ``run_dir``.

    ``frame_probs`` (CNN p_defect per frame) are fused with the 3D frame labels by ``fusion``
    (a ``detection.classifier.fusion.FusionRule``; None: ``cfg.fusion_threshold`` and the
    default context rule).

    Resumes: when RUN/detection.json records the same inputs and config, the files are read
    back instead of recomputed (``cfg.overwrite`` forces a recompute).
    """
    run_dir = Path(run_dir)
    mask = drive.camera.mask
    sig = signature(
        cfg, pairs, traj, run_dir, frame_probs, fusion, None if mask is None else mask.digest
    )
    if not cfg.overwrite:
        cached = load_result(run_dir, sig)
        if cached is not None:
            log.info("detection: outputs in %s are up to date, skipping", run_dir)
            return cached
    # the record goes first: a run stopped while rewriting leaves no record of the old result
    # beside new defect files and masks (a resume would trust them)
    (Path(run_dir) / DETECTION_JSON).unlink(missing_ok=True)
    with bounded_block_cache():  # surface.tif is read window by window: memory stays flat
        return _detect(cfg, drive, pairs, traj, run_dir, sig, frame_probs, fusion)


def _detect(
    cfg: DetectionConfig,
    drive: Drive,
    pairs: list[PairResult],
    traj: Trajectory,
    run_dir: Path,
    sig: str,
    frame_probs: dict[str, float] | None,
    fusion: FusionRule | None,
) -> DetectionResult:
    """``run`` after the resume check: steps 1-3 and the output files."""

    # ---- 1. per pair
    steps_s: dict[str, float] = {}  # wall time of the main steps, logged (docs/benchmarks.md)
    t0 = time.perf_counter()
    masks_dir = RunFolder(run_dir).masks_dir
    _clear_masks(masks_dir, drive)
    # With the map, the masks are the map's defects seen by each frame (step 3); without it
    # (frame_label "pair") each pair's refined 2D mask of image a.
    per_pair = analyse_pairs(
        cfg, drive, pairs, masks_dir=masks_dir if cfg.frame_label == "pair" else None
    )
    steps_s["pairs"] = time.perf_counter() - t0
    pose_of = {fn: i for i, fn in enumerate(traj.filenames)}
    ev_enu, ev_pair = evidence_points(pairs, per_pair, traj, pose_of)

    # ---- 2. global map, read in windows around the 3D evidence only
    surface, mframe = load_surface(cfg, run_dir, pairs, per_pair, traj, pose_of)
    defects: list[Defect] = []
    noise = seed = float("nan")
    footprints = frame_footprints(drive, traj, mframe)
    cells: list[DefectCells] = []
    warnings: list[str] = []
    if surface is not None:
        ev_xy = mframe.grid_from_enu(ev_enu) if len(ev_enu) else np.zeros((0, 2))
        if isinstance(surface, PointsSource):  # already read by load_surface
            pts = (surface.xy, surface.residual, surface.source)
        else:
            pts = depth_points(run_dir, pairs, per_pair, traj, pose_of, mframe)
        seeds_xy = ev_xy
        if not per_pair and pts is not None:
            # No pairs: windows around the deep map points (no per-pair evidence to seed them).
            deep = -pts[1] >= cfg.map.depth_threshold_m
            seeds_xy = pts[0][deep]
        dense_seeds = cfg.map.raster_seeds and per_pair and getattr(surface, "count_path", None)
        observed = (
            mapped_area(surface, pairs, footprints) if dense_seeds or cfg.rut.enabled else None
        )
        if dense_seeds:
            seeds_xy = np.vstack([seeds_xy, raster_seeds(surface, cfg.map, observed)])
        try:
            t0 = time.perf_counter()
            seg = segment_windows(
                surface, cfg.map, seeds_xy, ev_xy, ev_pair,
                # with the dense surface's counts a window around fewer points may still be
                # confirmed by two pairs' dense heights (measurement)
                min_points=cfg.map.min_support_points
                if per_pair and getattr(surface, "count_path", None) is None
                else 1,
            )  # fmt: skip
            steps_s["windows"] = time.perf_counter() - t0
            if cfg.rut.enabled:
                path = np.array([np.asarray(fp.centroid.coords[0]) for fp in footprints.values()])
                seeds = scan_seeds(
                    surface, path.reshape(-1, 2), cfg.rut, cfg.map,
                    observed=observed,
                )  # fmt: skip
                seg.regions = trace_ruts(
                    surface, seg.regions, cfg.rut, cfg.map, ev_xy, ev_pair, scan_seeds=seeds
                )
        finally:
            surface.close()
        noise, seed = seg.noise_m, seg.seed_m
        pair_pts = pair_points(pairs, per_pair, traj, pose_of, mframe)
        dense = None
        if cfg.dense.enabled and cfg.use_images and per_pair:
            grid = [
                (
                    k,
                    xy,
                    ~per_pair[k].candidate & (np.abs(per_pair[k].dist_m) < per_pair[k].threshold_m),
                )
                for k, (xy, _) in zip(pair_keys(per_pair, traj, pose_of), pair_pts, strict=True)
            ]
            sparse_noise = float(np.median([pd.noise_m for pd in per_pair.values()]))
            dense = DenseContext(drive, pairs, grid, sparse_noise, cfg.pair_workers)
        t0 = time.perf_counter()
        is_dense = isinstance(surface, RasterSource) and math.isfinite(surface.footprint_m)
        defects, cells = measure_regions(
            cfg,
            seg,
            footprints,
            bool(per_pair),
            None if pts is None else pts[:2],
            pair_pts=pair_pts,
            dense=dense,
            dense_raster=is_dense,
            raster_floor_m=surface.search_depth_m if is_dense else math.nan,
            warnings=warnings,
        )
        steps_s["measurement"] = time.perf_counter() - t0
        # cracks are measured across their centre line on the raster itself (reopened lazily)
        raster = surface if isinstance(surface, RasterSource) else None
        try:
            cracks = crack_defects(
                cfg, per_pair, traj, pose_of, mframe, footprints, defects, raster=raster
            )
        finally:
            surface.close()
        if cracks:
            # a crack's cells: its outline on a lattice fine enough for its width
            of = {id(d): c for d, c in zip(defects, cells, strict=True)}
            for d in cracks:
                step = float(np.clip(0.5 * d.width_m, 0.001, seg.grid.gsd_m))
                of[id(d)] = DefectCells(outline_cells(d.outline_xy_m, step), np.zeros((0, 2)), step)
            defects = renumber(defects + cracks, footprints)
            cells = [of[id(d)] for d in defects]
        log.info(
            "detection: %d defect(s) from %d region(s); map noise σ %.2f mm, T_d %.1f mm (%s)",
            len(defects),
            len(seg.regions),
            1000 * noise,
            1000 * seed,
            surface.source,
        )
    else:
        log.warning("detection: no surface raster and no points to rasterise; frame labels only")
    log.info("detection: steps (s) %s", ", ".join(f"{k} {v:.2f}" for k, v in steps_s.items()))

    # ---- 3. frame labels and masks
    views: dict[str, FrameView] = {}
    planes: dict[str, np.ndarray] = {}
    if surface is not None and cfg.frame_label == "map":
        # frames whose pose ties them to the map: those of an ok pair, and with GPS every frame
        in_pair = {fn for p in pairs if p.ok for fn in (p.frame_a, p.frame_b)}
        viewed = [f.filename for f in drive.frames if mframe.georeferenced or f.filename in in_pair]
        planes = road_planes(pairs, per_pair, traj, pose_of)
        views = frame_views(drive.camera, traj, mframe, viewed, footprints, cells, planes)
    pair_scores = pair_frame_scores(cfg, drive, pairs, per_pair)
    frames = frame_labels(cfg, drive, views, pair_scores)
    frames = fuse_labels(cfg, frames, frame_probs, pairs, fusion)
    if views:
        shown = write_frame_masks(masks_dir, drive.camera, traj, mframe, views, cells, planes)
        for j, d in enumerate(defects):
            d.frames = sorted(shown.get(j, []))

    result = DetectionResult(
        defects=defects,
        frames=frames,
        run_dir=run_dir,
        noise_m=noise,
        seed_threshold_m=seed,
        georeferenced=mframe.georeferenced,
        crs=mframe.crs,
        surface_source=surface.source if surface is not None else "none",
        warnings=warnings,
    )
    for w in warnings:
        log.warning("detection: %s", w)
    write_outputs(result, mframe, sig, to_dict(cfg))
    return result


def _clear_masks(masks_dir: Path, drive: Drive) -> None:
    """Remove the masks an earlier run wrote for this drive's frames (this stage writes them
    again; a frame it no longer views must not keep an old mask)."""
    for f in drive.frames:
        (masks_dir / f"{Path(f.filename).stem}.png").unlink(missing_ok=True)
