"""Detection stage entry point: per-pair 3D segmentation, global-map defects, GIS outputs.

``run(cfg, drive, pairs, traj, run_dir, *, frame_probs=None) -> DetectionResult`` writes
RUN/defects.geojson, RUN/defects.csv, RUN/frames.csv and RUN/detection.json (provenance and
resume state). See docs/detection.md.

Steps:
1. per pair: recursive plane fit (eq. 4.8-4.10) and CORRECT_DEFECTS (Fig. 4.3) -> refined
   defect points, placed in the map with the trajectory;
2. on the map: the residual surface raster (RUN/surface.tif, else rasterised points) is segmented
   by hysteresis thresholds relative to its measured noise, seeds and refined points are clustered
   with flat-kernel mean shift (eq. 5.11-5.12), and each defect is vetted by its 3D evidence and
   measured;
3. frame labels: the deep defect area inside each frame's footprint (the simulator's rule);
   fused with CNN probabilities when ``frame_probs`` is given.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from roadsurf.core.config import to_dict
from roadsurf.core.parallel import ordered_map
from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.footprint import footprint_enu
from roadsurf.detection.mapframe import MapFrame
from roadsurf.detection.mapseg import Measured, choose_gsd, classify, measure, severity
from roadsurf.detection.output import load_result, write_outputs
from roadsurf.detection.pairs import PairDefects, analyse_pair
from roadsurf.detection.types import Defect, DetectionResult, FrameLabel
from roadsurf.detection.windows import PointsSource, RasterSource, WindowSource, segment_windows
from roadsurf.io.drive import Drive, GrayFrames
from roadsurf.mapping.types import Trajectory
from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


def run(
    cfg: DetectionConfig,
    drive: Drive,
    pairs: list[PairResult],
    traj: Trajectory,
    run_dir: Path,
    *,
    frame_probs: dict[str, float] | None = None,
    fusion: Any = None,
) -> DetectionResult:
    """Detect and measure defects; write the output files into ``run_dir``.

    ``frame_probs`` (CNN p_defect per frame) are fused with the 3D frame labels by ``fusion``
    (a ``detection.classifier.fusion.FusionRule``; None: ``cfg.fusion_threshold`` and the
    default context rule).

    Resumes: when RUN/detection.json records the same inputs and config, the files are read
    back instead of recomputed (``cfg.overwrite`` forces a recompute).
    """
    run_dir = Path(run_dir)
    signature = _signature(cfg, pairs, traj, run_dir, frame_probs, fusion)
    if not cfg.overwrite:
        cached = load_result(run_dir, signature)
        if cached is not None:
            log.info("detection: outputs in %s are up to date, skipping", run_dir)
            return cached

    # ---- 1. per pair
    steps_s: dict[str, float] = {}  # wall time of the main steps, logged (docs/benchmarks.md)
    t0 = time.perf_counter()
    per_pair = analyse_pairs(cfg, drive, pairs, masks_dir=run_dir / "masks")
    steps_s["pairs"] = time.perf_counter() - t0
    pose_of = {fn: i for i, fn in enumerate(traj.filenames)}
    ev_enu, ev_pair = _evidence_points(pairs, per_pair, traj, pose_of)

    # ---- 2. global map, read in windows around the 3D evidence only
    surface, mframe = load_surface(cfg, run_dir, pairs, per_pair, traj, pose_of)
    defects: list[Defect] = []
    noise = seed = float("nan")
    footprints = _footprints(drive, traj, mframe)
    deep_xy: list[np.ndarray] = []
    if surface is not None:
        ev_xy = mframe.grid_from_enu(ev_enu) if len(ev_enu) else np.zeros((0, 2))
        if isinstance(surface, PointsSource):  # already read by load_surface
            pts = (surface.xy, surface.residual, surface.source)
        else:
            pts = _depth_points(run_dir, pairs, per_pair, traj, pose_of, mframe)
        seeds_xy = ev_xy
        if not per_pair and pts is not None:
            # No pairs: windows around the deep map points (no per-pair evidence to seed them).
            deep = -pts[1] >= cfg.map.depth_threshold_m
            seeds_xy = pts[0][deep]
        try:
            t0 = time.perf_counter()
            seg = segment_windows(
                surface, cfg.map, seeds_xy, ev_xy, ev_pair,
                min_points=cfg.map.min_support_points if per_pair else 1,
            )  # fmt: skip
            steps_s["windows"] = time.perf_counter() - t0
            if cfg.rut.enabled:
                from roadsurf.detection.ruts import scan_seeds, trace_ruts

                path = np.array([np.asarray(fp.centroid.coords[0]) for fp in footprints.values()])
                seeds = scan_seeds(
                    surface, path.reshape(-1, 2), cfg.rut, cfg.map,
                    observed=_mapped_area(surface, pairs, footprints),
                )  # fmt: skip
                seg.regions = trace_ruts(
                    surface, seg.regions, cfg.rut, cfg.map, ev_xy, ev_pair, scan_seeds=seeds
                )
        finally:
            surface.close()
        noise, seed = seg.noise_m, seg.seed_m
        pair_pts = _pair_points(pairs, per_pair, traj, pose_of, mframe)
        dense = None
        if cfg.dense.enabled and cfg.use_images and per_pair:
            from roadsurf.detection.dense import DenseContext

            grid = [
                (
                    k,
                    xy,
                    ~per_pair[k].candidate & (np.abs(per_pair[k].dist_m) < per_pair[k].threshold_m),
                )
                for k, (xy, _) in zip(_pair_keys(per_pair, traj, pose_of), pair_pts, strict=True)
            ]
            sparse_noise = float(np.median([pd.noise_m for pd in per_pair.values()]))
            dense = DenseContext(drive, pairs, grid, sparse_noise, cfg.pair_workers)
        t0 = time.perf_counter()
        defects, deep_xy = _measure_regions(
            cfg,
            seg,
            footprints,
            bool(per_pair),
            None if pts is None else pts[:2],
            pair_pts=pair_pts,
            dense=dense,
        )
        steps_s["measurement"] = time.perf_counter() - t0
        cracks = _crack_defects(cfg, per_pair, traj, pose_of, mframe, footprints, defects)
        if cracks:
            defects = _renumber(defects + cracks, footprints)
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

    # ---- 3. frame labels
    cell_m2 = surface.grid.gsd_m**2 if surface is not None else 0.0
    use_map = surface is not None and cfg.frame_label == "map"
    pair_scores = _pair_frame_scores(cfg, drive, pairs, per_pair)
    frames = _frame_labels(cfg, drive, footprints, deep_xy, cell_m2, pair_scores, use_map)
    frames = _fuse(cfg, frames, frame_probs, pairs, fusion)

    result = DetectionResult(
        defects=defects,
        frames=frames,
        run_dir=run_dir,
        noise_m=noise,
        seed_threshold_m=seed,
        georeferenced=mframe.georeferenced,
        crs=mframe.crs,
        surface_source=surface.source if surface is not None else "none",
    )
    write_outputs(result, mframe, signature, to_dict(cfg))
    return result


# --------------------------------------------------------------------------- per pair


def analyse_pairs(
    cfg: DetectionConfig,
    drive: Drive,
    pairs: list[PairResult],
    masks_dir: Path | None = None,
) -> dict[int, PairDefects]:
    """Plane fit + 2D/3D refinement of every ok pair; keyed by the pair's position in ``pairs``.

    With ``masks_dir`` the refined 2D defect mask of each pair's image a is written there as
    ``<frame stem>.png`` (uint8, 255 = defect, 0 = not) and not kept in memory.
    """
    out: dict[int, PairDefects] = {}
    ok = [(k, p) for k, p in enumerate(pairs) if p.ok]
    workers = max(1, int(cfg.pair_workers))
    # consecutive pairs share a frame (b, then a); each thread is a pair or two apart
    image = GrayFrames(
        drive.frames, 2 * workers + 2, "detection: pairs with this frame use 3D only"
    ).get

    def one(kp: tuple[int, PairResult]) -> PairDefects | None:
        _, p = kp
        gray = gray_b = None
        if cfg.use_images and cfg.refine.enabled:
            gray = image(p.frame_a)
            # Image b only for the dense crack depth (parallax across each crack).
            if gray is not None and cfg.crack.enabled and cfg.crack.dense:
                gray_b = image(p.frame_b)
        return analyse_pair(
            p, gray, cfg, m_per_px=drive.camera.height_m / drive.camera.fx,
            gray_b=gray_b, camera=drive.camera,
        )  # fmt: skip

    # pairs are independent: threads analyse them (NumPy and OpenCV release the GIL), and the
    # results are taken in pair order, so they are the same on any thread count
    results = ordered_map(one, ok, workers)
    bar = tqdm(total=len(ok), desc="detection: pairs", unit="pair", disable=len(ok) < 20)
    with bar:
        for (k, _), res in zip(ok, results, strict=True):
            bar.update(1)
            if res is None:
                continue
            if masks_dir is not None and res.mask is not None:
                _write_mask(Path(masks_dir) / f"{Path(res.frame_a).stem}.png", res.mask)
            res.mask = None  # bounded memory: a few image masks at a time
            out[k] = res
    return out


def _write_mask(path: Path, mask: np.ndarray) -> None:
    """Write a refined 2D defect mask as an 8-bit PNG (255 = defect), atomically."""
    import cv2

    from roadsurf.core.atomic import atomic_path

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.where(mask, 255, 0).astype(np.uint8)):
            raise OSError(f"{path}: could not write the defect mask PNG (disk full?)")


def _evidence_points(
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Defect points of all pairs in ENU (M, 3) and the pair id of each (M,): the refined
    points (2D + 3D) together with the plane fit's candidates, so that the 3D evidence of a
    defect that is not darker in the image still counts."""
    xyz, ids = [], []
    for k, pd in per_pair.items():
        i = pose_of.get(pd.frame_a)
        sel = pd.refined | pd.candidate
        if i is None or not sel.any():
            continue
        T = traj.world_from_cam[i]
        P = np.asarray(pairs[k].points_cam_a_m, float)[sel]
        xyz.append(P @ T[:3, :3].T + T[:3, 3])
        ids.append(np.full(len(P), k))
    if not xyz:
        return np.zeros((0, 3)), np.zeros(0, int)
    return np.vstack(xyz), np.concatenate(ids)


# --------------------------------------------------------------------------- map


def load_surface(
    cfg: DetectionConfig,
    run_dir: Path,
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
) -> tuple[WindowSource | None, MapFrame]:
    """The residual raster as a windowed source: RUN/surface.tif (or .vrt), else the map points
    or the pairs' points gridded per window. Nothing is read here."""
    for name in ("surface.tif", "surface.vrt"):
        path = run_dir / name
        if path.exists():
            src = RasterSource(path)
            mframe = MapFrame.create(traj.reference, src.grid.crs if traj.reference else None)
            return src, mframe
    mframe = MapFrame.create(traj.reference)
    pts = _depth_points(run_dir, pairs, per_pair, traj, pose_of, mframe)
    if pts is None:
        return None, mframe
    xy, resid, name = pts
    gsd = choose_gsd(xy, cfg.map.fallback_gsd_m)
    return PointsSource(xy, resid, gsd, mframe.crs, name), mframe


def _footprints(drive: Drive, traj: Trajectory, mframe: MapFrame) -> dict[str, Any]:
    """filename -> shapely Polygon of the frame's footprint in the grid frame."""
    from shapely.geometry import Polygon

    out: dict[str, Any] = {}
    corners, names = [], []
    for fn, T in zip(traj.filenames, traj.world_from_cam, strict=True):
        fp = footprint_enu(T, drive.camera)
        if fp is not None:
            corners.append(fp)
            names.append(fn)
    if not corners:
        return out
    xy = mframe.grid_from_enu(np.vstack(corners))
    for j, fn in enumerate(names):
        out[fn] = Polygon(xy[4 * j : 4 * j + 4])
    return out


def _mapped_area(surface: WindowSource, pairs: list[PairResult], footprints: dict[str, Any]) -> Any:
    """Where the map's surface raster can hold data: the footprints of the frames of every pair
    (the map is made of the pairs' points), grown by 0.5 m for the raster's fill; None (all of
    it) for a source gridded from other points."""
    if not isinstance(surface, RasterSource):
        return None
    from shapely import unary_union

    frames = {fn for p in pairs for fn in (p.frame_a, p.frame_b)}
    return unary_union([fp for fn, fp in footprints.items() if fn in frames]).buffer(0.5)


def _measure_regions(
    cfg: DetectionConfig,
    seg: Any,
    footprints: dict[str, Any],
    have_pairs: bool,
    points: tuple[np.ndarray, np.ndarray] | None = None,
    pair_pts: list[tuple[np.ndarray, np.ndarray]] | None = None,
    dense: Any = None,
) -> tuple[list[Defect], list[np.ndarray]]:
    """Veto regions without 3D evidence, measure the rest; ids ordered along the drive.

    ``points`` (grid xy (N, 2), residual (N,)): the 3D points, whose deepest value inside the
    outline gives the max depth (the raster interpolation and smoothing shave pothole bottoms).
    ``pair_pts`` (per pair: grid xy (N, 2), camera-a points (N, 3)): when pairs see the defect,
    its max depth is also measured in each pair's own frame (see ``pair_max_depth``), which the
    map's trajectory errors cannot distort, and the deeper of the two readings is kept; the map
    points alone are the fallback when no pair sees enough of the defect.
    """
    from shapely.geometry import Polygon

    mc = cfg.map
    gsd2 = seg.grid.gsd_m**2
    kept: list[tuple[Defect, np.ndarray]] = []
    for reg in seg.regions:
        seed_m = reg.seed_m if math.isfinite(reg.seed_m) else seg.seed_m
        noise_m = reg.noise_m if math.isfinite(reg.noise_m) else seg.noise_m
        deep_area = float((reg.depth_smooth_m >= seed_m).sum() * gsd2)
        max_depth = float(np.nanmax(reg.depth_smooth_m))
        rut = reg.rut
        if rut is not None:  # traced on straightedge profiles: its own depth and floor
            max_depth, deep_area = rut.max_depth_m, float(len(reg.rows) * gsd2)
        why = None
        if max_depth < (mc.min_depth_m if rut is None else cfg.rut.min_depth_m):
            why = f"shallow ({1000 * max_depth:.1f} mm)"
        elif deep_area < mc.min_area_m2:
            why = f"small ({1e4 * deep_area:.1f} cm²)"
        elif have_pairs and (
            len(reg.support_pairs) < mc.min_support_pairs
            or reg.n_support_points < mc.min_support_points
        ):
            why = f"{reg.n_support_points} defect point(s) from {len(reg.support_pairs)} pair(s)"
        if why:
            log.debug("detection: region at %s vetoed: %s", (reg.rows[0], reg.cols[0]), why)
            continue
        m = measure(reg, seg.grid, mc.frame_depth_m)
        poly = Polygon(m.outline_xy_m)
        dm = part = None
        if rut is not None:
            # Depths from the stations' averaged profiles (a noisy cell's maximum reads deep);
            # length along the centre line, width the median trough width.
            prof = np.clip(np.nan_to_num(reg.depth_smooth_m, nan=0.0), 0.0, None)
            m.max_depth_m = rut.max_depth_m
            m.mean_depth_m = float(prof.mean())
            m.volume_m3 = float(prof.sum() * gsd2)
            m.length_m = rut.length_m
            m.width_m = rut.body_width_m
        elif dense is not None:
            from roadsurf.detection.dense import measure_defect_dense

            dm = measure_defect_dense(
                poly, dense, cfg.dense, mc.rim_threshold_m, cfg.plane.max_depth_m
            )
            if dm is not None and dm.coverage < cfg.dense.min_coverage:
                dm, part = None, dm  # too partial to measure the defect by; see below
        if dm is not None:
            log.debug(
                "detection: dense %s: max %.1f mm (raster %.1f), area %.4f (raster %.4f) m²",
                m.centroid_xy_m, 1000 * dm.max_depth_m, 1000 * m.max_depth_m, dm.area_m2, m.area_m2,
            )  # fmt: skip
            m.max_depth_m = dm.max_depth_m
            m.mean_depth_m = dm.mean_depth_m
            m.volume_m3 = dm.volume_m3
            if cfg.dense.area:
                m.area_m2 = dm.area_m2
            # Frame labels count raster cells this deep: the dense depth where pairs tracked
            # the cell, else the raster's (interpolated, it shaves the bottom).
            xy_reg = seg.grid.xy_from_rowcol(reg.rows, reg.cols)
            d_reg = dm.depth_at(xy_reg)
            k = max(1.0, dm.max_depth_m / max(float(np.nanmax(reg.depth_smooth_m)), 1e-6))
            d_reg = np.fmax(d_reg, reg.depth_smooth_m * k)
            m.deep_xy_m = xy_reg[d_reg >= mc.frame_depth_m]
        elif points is not None and rut is None:
            pt_max = point_max_depth(poly, points[0], points[1], mc)
            if pair_pts:
                pr_max = pair_max_depth(poly, pair_pts, mc)
                if pr_max is not None:
                    # Both read low: the pairs sample the bottom sparsely, a pose error smears
                    # the map's copy (shallower). Neither can invent depth, so the larger wins.
                    pt_max = max(pr_max, pt_max or 0.0)
            if part is not None:
                # A partial dense reading still measured the part it saw: the same rule.
                pt_max = max(part.max_depth_m, pt_max or 0.0)
            log.debug(
                "detection: %s no full dense reading: map points %s, pairs %s, partial dense %s",
                m.centroid_xy_m, pt_max, pr_max if pair_pts else None,
                None if part is None else part.max_depth_m,
            )  # fmt: skip
            if pt_max is not None and pt_max > 0:
                # The raster's bottom is shaved by interpolation: scale its depths to the
                # points' before measuring the area deeper than the frame-label depth.
                k = max(1.0, pt_max / max(m.max_depth_m, 1e-6))
                deep = reg.depth_smooth_m * k >= mc.frame_depth_m
                m.deep_xy_m = seg.grid.xy_from_rowcol(reg.rows[deep], reg.cols[deep])
                m.max_depth_m = pt_max
                m.mean_depth_m *= k
                m.volume_m3 *= k
        kind = "rut" if rut is not None else classify(m, mc)
        seen = sorted(fn for fn, fp in footprints.items() if fp.intersects(poly))
        snr = max_depth / max(noise_m, 1e-6)
        n_views = len(reg.support_pairs) if have_pairs else len(seen)
        conf = (1.0 - math.exp(-snr / 6.0)) * (1.0 - 0.5 ** (n_views + 1))
        d = Defect(
            id=0,
            type=kind,
            severity=severity(kind, m, cfg.severity),
            outline_xy_m=m.outline_xy_m,
            centroid_xy_m=m.centroid_xy_m,
            max_depth_m=m.max_depth_m,
            mean_depth_m=m.mean_depth_m,
            area_m2=m.area_m2,
            volume_m3=m.volume_m3,
            length_m=m.length_m,
            width_m=m.width_m,
            confidence=float(np.clip(conf, 0.0, 1.0)),
            frames=seen,
        )
        kept.append((d, m.deep_xy_m))
    order = {fn: i for i, fn in enumerate(footprints)}
    kept.sort(
        key=lambda t: (min((order[f] for f in t[0].frames), default=1 << 30), t[0].centroid_xy_m[0])
    )
    for i, (d, _) in enumerate(kept, start=1):
        d.id = i
    return [d for d, _ in kept], [x for _, x in kept]


def _renumber(defects: list[Defect], footprints: dict[str, Any]) -> list[Defect]:
    """Ids ordered along the drive (first frame that saw the defect, then easting)."""
    order = {fn: i for i, fn in enumerate(footprints)}
    defects = sorted(
        defects,
        key=lambda d: (min((order[f] for f in d.frames), default=1 << 30), d.centroid_xy_m[0]),
    )
    for i, d in enumerate(defects, start=1):
        d.id = i
    return defects


def _crack_defects(
    cfg: DetectionConfig,
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
    mframe: MapFrame,
    footprints: dict[str, Any],
    others: list[Defect],
) -> list[Defect]:
    """Cracks confirmed per pair, placed in the map and clustered (one crack seen by several
    pairs is one defect); pieces inside a map defect's outline belong to that defect."""
    from shapely import contains_xy, union_all
    from shapely.geometry import MultiPoint, Polygon

    from roadsurf.detection.cracks import cluster_cracks, crack_evidence

    xy_l, pair_l, piece_l, pieces = [], [], [], []
    for k, pd in per_pair.items():
        c = pd.cracks
        i = pose_of.get(pd.frame_a)
        if c is None or i is None or not len(c.label):
            continue
        T = traj.world_from_cam[i]
        xy_l.append(mframe.grid_from_enu(c.xyz_cam_m @ T[:3, :3].T + T[:3, 3]))
        pair_l.append(np.full(len(c.label), k))
        piece_l.append(c.label + len(pieces))
        for j in range(len(c.width_m)):
            # Sparse points and dense samples across the crack pool into one test, each sample
            # weighted by its inverse variance (w = n / σ² per source: Σ w d = S n / V,
            # Σ w = n² / V for a sum S of n samples with variance V).
            wd = wsum = 0.0
            for S, n, V in ((c.sum_depth_m[j], c.n_points[j], c.var_m2[j]),
                            (c.dense_sum_m[j], c.dense_n[j], c.dense_var_m2[j])):  # fmt: skip
                if n > 0 and V > 0:
                    wd, wsum = wd + S * n / V, wsum + n * n / V
            pieces.append(
                (c.width_m[j], wd, c.n_points[j] + c.dense_n[j], c.n_below[j] + c.dense_below[j],
                 wsum, c.max_depth_m[j])
            )  # fmt: skip
    if not xy_l:
        return []
    xy = np.vstack(xy_l)
    pair = np.concatenate(pair_l)
    piece = np.concatenate(piece_l)
    pc = np.asarray(pieces, float)
    lab = cluster_cracks(xy, cfg.crack.link_m)
    taken = [Polygon(d.outline_xy_m).buffer(0.01) for d in others]
    taken_all = union_all(taken) if taken else None
    out: list[Defect] = []

    def evidence(sel: np.ndarray) -> tuple[bool, float]:
        ids = np.unique(piece[sel])
        wsum = pc[ids, 4].sum()
        if wsum <= 0:
            return False, 0.0
        # The weighted mean Σ w d / Σ w and its variance 1 / Σ w: z = Σ w d / √(Σ w).
        return crack_evidence(
            pc[ids, 1].sum() / wsum, int(pc[ids, 2].sum()), int(pc[ids, 3].sum()), 1.0 / wsum,
            cfg.crack,
        )  # fmt: skip

    # Confirmed cracks whose samples come within ``join_m`` are one crack (a crack is often
    # confirmed in pieces where the texture hides its middle from the 2D detector).
    confirmed = [c for c in np.unique(lab) if evidence(lab == c)[0] and (lab == c).sum() >= 3]
    if len(confirmed) > 1:
        keep = np.isin(lab, confirmed)
        joined = cluster_cracks(xy[keep], cfg.crack.join_m)
        first = {}
        for c, j in zip(lab[keep].tolist(), joined.tolist(), strict=True):
            first.setdefault(j, c)
        lab = lab.copy()
        lab[keep] = [first[j] for j in joined.tolist()]
        confirmed = sorted(set(first.values()))
    close = cfg.crack.join_m / 2
    for c in confirmed:
        sel = lab == c
        p = xy[sel]
        ids = np.unique(piece[sel])
        ok, z = evidence(sel)
        if not ok:
            continue
        # A crack sample inside a map defect's outline: the piece belongs to that defect.
        # Checked on the samples before the costly buffer (pothole rims give many such pieces).
        if taken_all is not None and contains_xy(taken_all, p[:, 0], p[:, 1]).any():
            continue
        w = float(np.median(pc[ids, 0]))
        # Outline: the samples dilated by half the width, then closed by ``close`` (the same set
        # as dilating by half the width + close and eroding by close, but the union of hundreds
        # of 10 cm discs cost seconds per crack; samples snapped to 1 mm first).
        snap = np.unique(np.round(p / 0.001), axis=0) * 0.001
        geom = MultiPoint(snap).buffer(max(0.5 * w, 0.003)).buffer(close).buffer(-close)
        if geom.geom_type != "Polygon":
            geom = max(geom.geoms, key=lambda g: g.area)
        if any(t.intersects(geom) for t in taken):
            continue
        (_, _), (a, b), _ = cv2.minAreaRect((p - p.mean(axis=0)).astype(np.float32))
        length = float(max(a, b)) + w
        # Robust max: the median over the pieces of each piece's second-deepest point.
        dmax = float(np.median(pc[ids, 5]))
        if dmax > cfg.plane.max_depth_m:
            # Deeper than any defect the plane fit accepts: the pooled "evidence" comes from a
            # failed reconstruction (decimetre noise), not from a crack.
            continue
        # Parabolic groove profile (1 - q²): the mean over the width is 2/3 of the centre depth.
        dmean = dmax * 2.0 / 3.0
        area = length * w
        n_pairs = len(np.unique(pair[sel]))
        conf = (1.0 - math.exp(-z / 6.0)) * (1.0 - 0.5 ** (n_pairs + 1))
        seen = sorted(fn for fn, fp in footprints.items() if fp.intersects(geom))
        m = Measured(
            outline_xy_m=np.asarray(geom.exterior.coords)[:-1],
            centroid_xy_m=p.mean(axis=0),
            max_depth_m=dmax,
            mean_depth_m=dmean,
            area_m2=area,
            volume_m3=area * dmean,
            length_m=length,
            width_m=w,
            deep_xy_m=np.zeros((0, 2)),
        )
        out.append(
            Defect(
                id=0,
                type="crack",
                severity=severity("crack", m, cfg.severity),
                outline_xy_m=m.outline_xy_m,
                centroid_xy_m=m.centroid_xy_m,
                max_depth_m=dmax,
                mean_depth_m=dmean,
                area_m2=area,
                volume_m3=m.volume_m3,
                length_m=length,
                width_m=w,
                confidence=float(np.clip(conf, 0.0, 1.0)),
                frames=seen,
            )
        )
    if out:
        log.info("detection: %d crack(s) from %d confirmed piece(s)", len(out), len(np.unique(lab)))
    return out


def _depth_points(
    run_dir: Path,
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
    mframe: MapFrame,
) -> tuple[np.ndarray, np.ndarray, str] | None:
    """The 3D points with their residual (m, negative below) in the grid frame, and where they
    came from: the fused map points (RUN/map_points.npz) when mapping wrote them, else every
    pair's points ("pairs")."""
    mp = run_dir / "map_points.npz"
    if mp.exists():
        with np.load(mp, allow_pickle=False) as z:
            if len(z["xyz"]):
                xy = mframe.grid_from_enu(np.asarray(z["xyz"], float))
                return xy, np.asarray(z["residual_m"], float), "map_points.npz"
    xyz_l, res_l = [], []
    for k, pd in per_pair.items():
        i = pose_of.get(pd.frame_a)
        if i is None:
            continue
        T = traj.world_from_cam[i]
        xyz_l.append(np.asarray(pairs[k].points_cam_a_m, float) @ T[:3, :3].T + T[:3, 3])
        res_l.append(pd.dist_m)
    if not xyz_l:
        return None
    return mframe.grid_from_enu(np.vstack(xyz_l)), np.concatenate(res_l), "pairs"


def point_max_depth(poly: Any, xy: np.ndarray, residual: np.ndarray, mc: Any) -> float | None:
    """Deepest point inside ``poly`` relative to the median road level in a ring around it.

    An isolated deepest point (deeper than the next by more than max(5 mm, 20 %)) is taken for
    a mismatch and the next one is used. None with fewer than ``min_support_points`` inside.
    """
    from shapely import contains_xy

    x0, y0, x1, y1 = poly.bounds
    pad = mc.level_ring_m
    near = (xy[:, 0] >= x0 - pad) & (xy[:, 0] <= x1 + pad) & (xy[:, 1] >= y0 - pad)
    near &= xy[:, 1] <= y1 + pad
    if not near.any():
        return None
    p, r = xy[near], residual[near]
    ins = contains_xy(poly, p[:, 0], p[:, 1])
    if ins.sum() < max(3, mc.min_support_points):
        return None
    ring = contains_xy(poly.buffer(pad), p[:, 0], p[:, 1]) & ~contains_xy(
        poly.buffer(0.03), p[:, 0], p[:, 1]
    )
    level = float(np.median(r[ring])) if ring.sum() >= 10 else 0.0
    d = np.sort(level - r[ins])[::-1]
    if d[0] - d[1] > max(0.005, 0.2 * d[1]):
        return float(d[1])
    return float(d[0])


def _pair_keys(
    per_pair: dict[int, PairDefects], traj: Trajectory, pose_of: dict[str, int]
) -> list[int]:
    """The pair indices ``_pair_points`` returns points for, in its order."""
    return [k for k, pd in per_pair.items() if pose_of.get(pd.frame_a) is not None]


def _pair_points(
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
    mframe: MapFrame,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per ok pair: its points' grid xy (N, 2) via the trajectory (to select them only) and the
    same points in the pair's own camera-a frame (N, 3), where depths are measured."""
    out = []
    for k, pd in per_pair.items():
        i = pose_of.get(pd.frame_a)
        if i is None:
            continue
        T = traj.world_from_cam[i]
        P = np.asarray(pairs[k].points_cam_a_m, float)
        out.append((mframe.grid_from_enu(P @ T[:3, :3].T + T[:3, 3]), P))
    return out


def pair_max_depth(
    poly: Any, pair_pts: list[tuple[np.ndarray, np.ndarray]], mc: Any
) -> float | None:
    """Max depth of the defect inside ``poly`` measured in each pair's OWN frame.

    Each pair whose points cover the outline: a robust plane through its road points in a ring
    (``level_ring_m`` wide) around the outline, and the deepest of its points inside. The pairs that see most of the defect (at least
    80 % of the best pair's points inside) are combined by their median. A pair's relative
    geometry is accurate to ~2 mm, while the fused map's trajectory error shifts the walls.
    None when no pair has ``min_support_points`` inside and a ring of road points.
    """
    from shapely import contains_xy

    from roadsurf.detection.planefit import robust_plane, signed_distance

    x0, y0, x1, y1 = poly.bounds
    pad = mc.level_ring_m
    outer, inner = poly.buffer(pad), poly.buffer(0.03)
    est: list[tuple[int, float]] = []
    for xy, P in pair_pts:
        near = (xy[:, 0] >= x0 - pad) & (xy[:, 0] <= x1 + pad) & (xy[:, 1] >= y0 - pad)
        near &= xy[:, 1] <= y1 + pad
        if near.sum() < 20:
            continue
        q, Q = xy[near], P[near]
        ins = contains_xy(poly, q[:, 0], q[:, 1])
        ring = contains_xy(outer, q[:, 0], q[:, 1]) & ~contains_xy(inner, q[:, 0], q[:, 1])
        if ins.sum() < max(3, mc.min_support_points) or ring.sum() < 20:
            continue
        plane = robust_plane(Q[ring])
        if plane is None:
            continue
        # The deepest point: the points sample a pothole's bottom sparsely, so lower
        # percentiles under-read it (bench: 2nd-deepest 4.4 mm MAE vs 3.5 mm); a single pair's
        # mismatch is voted out by the median over pairs.
        est.append((int(ins.sum()), float(-signed_distance(Q[ins], plane).min())))
    if not est:
        return None
    n_best = max(n for n, _ in est)
    return float(np.median([v for n, v in est if n >= 0.8 * n_best]))


# --------------------------------------------------------------------------- frames


def _frame_labels(
    cfg: DetectionConfig,
    drive: Drive,
    footprints: dict[str, Any],
    deep_xy: list[np.ndarray],
    cell_m2: float,
    pair_score: dict[str, float],
    have_map: bool,
) -> list[FrameLabel]:
    """Deep defect area in each frame's footprint (map), or the pairs' estimate without a map."""
    from matplotlib.path import Path as MplPath

    a_min = cfg.map.frame_min_area_m2
    pts = np.vstack(deep_xy) if deep_xy else np.zeros((0, 2))
    out: list[FrameLabel] = []
    for f in drive.frames:
        fp = footprints.get(f.filename)
        if have_map and fp is not None:
            area = 0.0
            if len(pts):
                x0, y0, x1, y1 = fp.bounds
                sel = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
                if sel.any():
                    inside = MplPath(np.asarray(fp.exterior.coords)).contains_points(pts[sel])
                    area = float(inside.sum()) * cell_m2
            p = area / (area + a_min) if area > 0 else 0.0
        else:
            p = pair_score.get(f.filename, 0.0)
        out.append(FrameLabel(f.filename, int(p >= 0.5), float(p), "3d"))
    return out


def _pair_frame_scores(
    cfg: DetectionConfig,
    drive: Drive,
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
) -> dict[str, float]:
    """The dissertation's per-frame decision from refined points alone.

    Frame k is seen by pair (k-1, k) (its pixels px_b) and pair (k, k+1) (px_a), which together
    cover its whole image. The deep refined points of both are binned on an image grid whose
    cells are one point spacing wide, and the occupied cells give the deep area.
    """
    m_per_px = drive.camera.height_m / drive.camera.fx
    items: dict[str, list[tuple[np.ndarray, float]]] = {}
    for k, pd in per_pair.items():
        p = pairs[k]
        deep = pd.refined & (-pd.dist_m >= cfg.map.frame_depth_m)
        for fn, px in ((p.frame_a, p.px_a), (p.frame_b, p.px_b)):
            lst = items.setdefault(fn, [])
            if deep.any():
                lst.append((np.asarray(px, float)[deep], pd.area_per_point_m2))
    a_min = cfg.map.frame_min_area_m2
    scores: dict[str, float] = {}
    for fn, lst in items.items():
        n = sum(len(px) for px, _ in lst)
        if n < 3:
            scores[fn] = 0.0
            continue
        app = float(np.median([a for _, a in lst]))
        s_px = max(1.0, math.sqrt(app) / m_per_px)
        cells = np.unique(np.floor(np.vstack([px for px, _ in lst]) / s_px).astype(int), axis=0)
        area = len(cells) * (s_px * m_per_px) ** 2
        scores[fn] = area / (area + a_min)
    return scores


def _fuse(
    cfg: DetectionConfig,
    frames: list[FrameLabel],
    frame_probs: dict[str, float] | None,
    pairs: list[PairResult],
    rule: Any = None,
) -> list[FrameLabel]:
    """Fig. 5.6: a confident CNN decides, otherwise 3D (frames no ok pair covers have no 3D)."""
    if not frame_probs:
        return frames
    from roadsurf.detection.classifier.fusion import FusionRule, fuse_frames

    if rule is None:
        rule = FusionRule(threshold=cfg.fusion_threshold)
    covered = {p.frame_a for p in pairs if p.ok} | {p.frame_b for p in pairs if p.ok}
    labels_3d = {f.filename: bool(f.defect) for f in frames if f.filename in covered}
    fused = fuse_frames(
        frame_probs,
        labels_3d,
        [f.filename for f in frames],
        rule.threshold,
        rule.confirm_defect_with_3d,
        rule.context_frames,
        rule.decide_3d,
    )
    out = []
    for f in frames:
        d = fused[f.filename]
        p = d.p_defect if d.source == "cnn" else f.p_defect if d.source == "3d" else d.p_defect
        if not math.isfinite(p):
            p = f.p_defect
        out.append(FrameLabel(f.filename, int(d.defect), float(p), d.source))
    return out


# --------------------------------------------------------------------------- resume


def _signature(
    cfg: DetectionConfig,
    pairs: list[PairResult],
    traj: Trajectory,
    run_dir: Path,
    frame_probs: dict[str, float] | None,
    fusion: Any = None,
) -> str:
    """Hash of everything the outputs depend on (config, pairs, poses, raster, CNN scores)."""
    h = hashlib.sha256()
    h.update(json.dumps(to_dict(cfg), sort_keys=True).encode())
    for p in pairs:
        h.update(f"{p.frame_a}|{p.frame_b}|{p.status}|{p.n_points}|{p.method}".encode())
        if p.n_points:
            h.update(np.ascontiguousarray(p.plane_dist_m, dtype=np.float64).tobytes()[:4096])
    h.update(np.ascontiguousarray(traj.world_from_cam, dtype=np.float64).tobytes())
    h.update(json.dumps(traj.reference.to_dict() if traj.reference else None).encode())
    for name in ("surface.tif", "surface.vrt", "map_points.npz"):
        p = Path(run_dir) / name
        if p.exists():
            st = p.stat()
            h.update(f"{name}|{st.st_size}|{st.st_mtime_ns}".encode())
    h.update(json.dumps(sorted((frame_probs or {}).items())).encode())
    if fusion is not None:
        h.update(
            repr((fusion.threshold, fusion.confirm_defect_with_3d, fusion.context_frames)).encode()
        )
        h.update(json.dumps(sorted(fusion.decide_3d)).encode())
    return h.hexdigest()
