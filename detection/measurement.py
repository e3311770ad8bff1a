"""Map regions -> measured defects: veto regions without 3D evidence, measure the rest (dense
reading, map points, pair frames or the rut's profiles), and number them along the drive.

The raster interpolates between the 3D points and smooths, which shaves pothole bottoms; so a
defect's max depth comes from the dense tracks when they cover it, else from the deepest 3D
points inside its outline (the map's and each pair's own, ``point_max_depth`` and
``pair_max_depth``; the map's only as far as the pairs support it), the raster's depths scaled
to match. Where the raster is the fused dense surface, its own reading also counts, with or
without a full track reading (the deeper wins), and the tracks count only as far as it supports
them. Every one of these maxima is a supported maximum (``roadsurf.detection.robust``): one
outlier point or cell cannot set it. A region is judged shallow by the raster's supported max
(``mapseg.raster_max_depth``), the statistic it is measured by, not by the smoothed raster.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.fits import plane_signed_distance, robust_plane_z
from roadsurf.detection.config import DetectionConfig, MapSegmentConfig
from roadsurf.detection.dense import DenseContext, measure_defect_dense
from roadsurf.detection.framemasks import DefectCells
from roadsurf.detection.mapseg import (
    Region,
    Segmentation,
    classify,
    measure,
    raster_max_depth,
    severity,
)
from roadsurf.detection.robust import POINT_SUPPORT, supported_by, supported_max
from roadsurf.detection.types import Defect

if TYPE_CHECKING:
    from shapely.geometry import Polygon

log = logging.getLogger(__name__)

# a dense surface reading this share of its search depth or more has reached it (the fused,
# smoothed heights of a floor at the bound read 107-128 mm for a 120 mm search)
CLIPPED_SHARE = 0.9
CLIPPED_SLACK_M = 0.015  # ... and at most this beyond it (m): the matching refuses 1 cm beyond


def measure_regions(
    cfg: DetectionConfig,
    seg: Segmentation,
    footprints: dict[str, Polygon],
    have_pairs: bool,
    points: tuple[np.ndarray, np.ndarray] | None = None,
    pair_pts: list[tuple[np.ndarray, np.ndarray]] | None = None,
    dense: DenseContext | None = None,
    dense_raster: bool = False,
    raster_floor_m: float = math.nan,
    warnings: list[str] | None = None,
) -> tuple[list[Defect], list[DefectCells]]:
    """Veto regions without 3D evidence, measure the rest; ids ordered along the drive.

    ``dense_raster``: the map's raster is the fused dense surface (surface.tif with a
    ``DENSE_FOOTPRINT_M`` tag), whose supported max then also bounds a dense-track reading -
    except where it reaches ``raster_floor_m`` (its matching's deepest search, the
    ``DENSE_SEARCH_DEPTH_M`` tag; NaN: unknown), below which it cannot read. Such a defect, and
    one dropped as deeper than ``plane.max_depth_m``, adds a line to ``warnings``.

    Returns the defects and, for each, its map cells (``DefectCells``: the cells deeper than
    the map's T_d that its 2D masks show, a rut's whole trace, and the cells deeper than
    ``frame_depth_m`` that frame labels count).

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
    kept: list[tuple[Defect, DefectCells]] = []
    for reg in seg.regions:
        seed_m = reg.seed_m if math.isfinite(reg.seed_m) else seg.seed_m
        noise_m = reg.noise_m if math.isfinite(reg.noise_m) else seg.noise_m
        deep_area = float((reg.depth_smooth_m >= seed_m).sum() * gsd2)
        # Judged by the statistic it is measured by (``raster_max_depth``: unsmoothed, supported
        # by CELL_SUPPORT cells) as well as the smoothed one: the smoothing of the thresholds
        # shaves the bottom of a pothole only a few times its σ wide (real photographs: an
        # 11 x 7 cm pothole read 8.6 mm smoothed and was dropped as shallow before the dense
        # tracks could measure it).
        max_depth = max(float(np.nanmax(reg.depth_smooth_m)), raster_max_depth(reg))
        rut = reg.rut
        if rut is not None:  # traced on straightedge profiles: its own depth and floor
            max_depth, deep_area = rut.max_depth_m, float(len(reg.rows) * gsd2)
        # The raster interpolates between sparse points and smooths: a narrow defect reads
        # small on it, so a small region with a dense reading is judged on that (below).
        small = deep_area < mc.min_area_m2
        why = None
        if max_depth < (mc.min_depth_m if rut is None else cfg.rut.min_depth_m):
            why = f"shallow ({1000 * max_depth:.1f} mm)"
        elif (
            have_pairs
            # a traced rut is its own evidence (straightedge profiles over metres): its points
            # are counted below the pairs' T_d, which a rough road lifts above a 10 mm rut
            # (unevenness 4 mm: T_d 13.9 mm, the rut traced at 11.8 mm and dropped)
            and rut is None
            and (
                len(reg.support_pairs) < mc.min_support_pairs
                or reg.n_support_points < mc.min_support_points
            )
            # ... unless two pairs' dense heights agree on it over the minimum area: small
            # potholes of a tilted camera hold 2 sparse points (variation sweep)
            and reg.dense_support_m2 < max(mc.min_area_m2, 1e-12)
        ):
            why = f"{reg.n_support_points} defect point(s) from {len(reg.support_pairs)} pair(s)"
        elif small and (rut is not None or dense is None):
            why = f"small ({1e4 * deep_area:.1f} cm²)"
        if why:
            _vetoed(seg, reg, why)
            continue
        m = measure(reg, seg.grid, mc.frame_depth_m)
        raster_max = m.max_depth_m  # the raster's supported max (CELL_SUPPORT cells)
        # the surface at its search depth reads no deeper: it bounds no deeper reading (a pair
        # matched again deeper, reconstruction.dense, reads beyond it)
        clipped = dense_raster and (
            CLIPPED_SHARE * raster_floor_m <= raster_max <= raster_floor_m + CLIPPED_SLACK_M
        )
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
            dm = measure_defect_dense(
                poly, dense, cfg.dense, mc.rim_threshold_m, cfg.plane.max_depth_m
            )
            if dm is not None and dm.coverage < cfg.dense.min_coverage:
                dm, part = None, dm  # too partial to measure the defect by; see below
            if small and (dm is None or dm.area_deeper(seed_m) < mc.min_area_m2):
                a = None if dm is None else 1e4 * dm.area_deeper(seed_m)
                _vetoed(seg, reg, f"small ({1e4 * deep_area:.1f} cm², dense {a} cm²)")
                continue
        if dm is not None:
            log.debug(
                "detection: dense %s: max %.1f mm (raster %.1f), area %.4f (raster %.4f) m²",
                m.centroid_xy_m, 1000 * dm.max_depth_m, 1000 * m.max_depth_m, dm.area_m2, m.area_m2,
            )  # fmt: skip
            m.max_depth_m = dm.max_depth_m
            tracks_ok = True
            if dense_raster:
                # The fused dense surface saw the floor from every pair (the nearest, least
                # oblique views too); one pair's tracks of a tilted camera read it shallower
                # (tilted 45° drive, potholes: 6.8 mm vs 4.2 mm MAE). The deeper wins, as for
                # the points below - and as there, only as far as the other reading supports
                # it: the tracks and the fused surface are two matchers of the same images, so
                # tracks deeper than the surface supports come from a pair whose tracks failed
                # over the floor (real photographs turned by 60°: a pair with 3x the others'
                # dense σ read 65 mm where the surface read 40 mm).
                if not clipped and not supported_by(dm.max_depth_m, raster_max):
                    log.debug(
                        "detection: %s dense tracks read %.1f mm, unsupported by the dense "
                        "surface's %.1f mm", m.centroid_xy_m, 1000 * dm.max_depth_m,
                        1000 * raster_max,
                    )  # fmt: skip
                    m.max_depth_m = raster_max
                    tracks_ok = False
                m.max_depth_m = max(m.max_depth_m, raster_max)
            if tracks_ok:  # else the raster's own mean and volume: the tracks read too deep
                m.mean_depth_m = dm.mean_depth_m
                m.volume_m3 = dm.volume_m3
            if cfg.dense.area:
                # within the outline it is reported with: on real photographs the noisier
                # cells of the 3 cm ring read deeper than the rim and doubled some areas
                m.area_m2 = min(dm.area_m2, float(poly.area))
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
                    # the map's copy (shallower), so the larger wins - unless the map reads
                    # deeper than the pairs support: its points are the pairs' points placed
                    # by the trajectory, and a depth the pairs do not see in their own frames
                    # comes from the placement (two stretches of road fused into one place).
                    if pt_max is not None and not supported_by(pt_max, pr_max):
                        log.debug(
                            "detection: %s map points read %.1f mm, unsupported by the pairs' "
                            "%.1f mm", m.centroid_xy_m, 1000 * pt_max, 1000 * pr_max,
                        )  # fmt: skip
                        pt_max = pr_max
                    pt_max = max(pr_max, pt_max or 0.0)
            if part is not None:
                # A partial dense reading still measured the part it saw: the same rules.
                part_max = part.max_depth_m
                if dense_raster and not clipped and not supported_by(part_max, raster_max):
                    part_max = raster_max
                pt_max = max(part_max, pt_max or 0.0)
            if dense_raster:
                # The fused dense surface measured the floor the tracks did not cover (LK
                # tracks on a smooth floor do not come back: real photographs, 44-59 % of the
                # outline tracked, the points and partial tracks on its rim 12-20 mm): the
                # deeper wins, as with a full dense reading.
                pt_max = max(pt_max or 0.0, raster_max)
            log.debug(
                "detection: %s no full dense reading: map points %s, pairs %s, partial dense "
                "%s, dense surface %s", m.centroid_xy_m, pt_max, pr_max if pair_pts else None,
                None if part is None else part.max_depth_m, raster_max if dense_raster else None,
            )  # fmt: skip
            if pt_max is not None and pt_max > 0:
                # The raster's bottom is shaved by interpolation: scale its depths to the
                # points' before measuring the area deeper than the frame-label depth. The
                # smoothed depths by their own max (as with a dense reading): the smoothing
                # shaves a narrow pothole further (real photographs, a pothole 4.5 cm wide read
                # 19 mm: 17 cm² deeper than 10 mm scaled by the raw max, 26 cm² by its own).
                k = max(1.0, pt_max / max(m.max_depth_m, 1e-6))
                ks = max(1.0, pt_max / max(float(np.nanmax(reg.depth_smooth_m)), 1e-6))
                deep = reg.depth_smooth_m * ks >= mc.frame_depth_m
                m.deep_xy_m = seg.grid.xy_from_rowcol(reg.rows[deep], reg.cols[deep])
                m.max_depth_m = pt_max
                m.mean_depth_m *= k
                m.volume_m3 *= k
        if rut is None and m.max_depth_m < mc.min_depth_m:
            # the same rule as above, on the measurement (the raster's noise can reach the
            # threshold where the dense tracks or the points measure a flat road)
            _vetoed(seg, reg, f"shallow as measured ({1000 * m.max_depth_m:.1f} mm)")
            continue
        e, n = (float(v) for v in m.centroid_xy_m)
        # the fused dense surface itself reads it that deep, having searched that deep (a pair
        # over a deep floor is matched again deeper): a pothole, not the points of a failed
        # reconstruction (the battery's 288 mm pothole, read 262 mm by the surface, was dropped)
        surface_deep = (
            dense_raster
            and raster_floor_m > cfg.plane.max_depth_m
            and supported_by(m.max_depth_m, raster_max)
        )
        if m.max_depth_m > cfg.plane.max_depth_m and not surface_deep:
            # Deeper than any defect the plane fit accepts (its mismatch bound): made of a
            # failed reconstruction's points, as for cracks (``crackmap``) - said, not silent:
            # a very deep pothole whose surface does not read it is dropped the same way
            _vetoed(seg, reg, f"deeper than a defect can be ({1000 * m.max_depth_m:.0f} mm)")
            if warnings is not None:
                warnings.append(
                    f"a region at E {e:.2f}, N {n:.2f} m measured {1000 * m.max_depth_m:.0f} mm "
                    f"deep was dropped: deeper than detection.plane.max_depth_m "
                    f"({1000 * cfg.plane.max_depth_m:.0f} mm), the bound on mismatched points. "
                    "If a pothole that deep is plausible there, raise it"
                )
            continue
        if clipped and warnings is not None:
            warnings.append(
                f"the defect at E {e:.2f}, N {n:.2f} m reaches the dense surface's deepest search depth "
                f"({1000 * raster_floor_m:.0f} mm below the road: mapping.dense.max_depth_m, or "
                "mapping.dense.max_depth_limit_m for a pair whose floor reached it, at most half "
                "the camera height): "
                f"the surface reads {1000 * raster_max:.0f} mm, the detector's own reading "
                f"{1000 * m.max_depth_m:.0f} mm; its depth may be a lower bound and its area and "
                "volume come from a surface cut flat at that depth. Raise those settings for "
                "this road"
            )
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
            mean_depth_m=min(m.mean_depth_m, m.max_depth_m),
            area_m2=m.area_m2,
            volume_m3=m.volume_m3,
            length_m=m.length_m,
            width_m=m.width_m,
            confidence=float(np.clip(conf, 0.0, 1.0)),
            frames=seen,
        )
        # The mask shows where the map is measurably below the road (T_d, the seed threshold the
        # defect was found at); a rut, shallower than T_d, is its traced trough.
        show = np.ones(len(reg.rows), bool) if rut is not None else reg.depth_smooth_m >= seed_m
        cells = DefectCells(
            seg.grid.xy_from_rowcol(reg.rows[show], reg.cols[show]), m.deep_xy_m, seg.grid.gsd_m
        )
        kept.append((d, cells))
    order = {fn: i for i, fn in enumerate(footprints)}
    kept.sort(
        key=lambda t: (min((order[f] for f in t[0].frames), default=1 << 30), t[0].centroid_xy_m[0])
    )
    for i, (d, _) in enumerate(kept, start=1):
        d.id = i
    return [d for d, _ in kept], [x for _, x in kept]


def _vetoed(seg: Segmentation, reg: Region, why: str) -> None:
    c = seg.grid.xy_from_rowcol(reg.rows, reg.cols).mean(axis=0)
    log.debug("detection: region at %s m vetoed: %s", np.round(c, 3), why)


def renumber(defects: list[Defect], footprints: dict[str, Polygon]) -> list[Defect]:
    """Ids ordered along the drive (first frame that saw the defect, then easting)."""
    order = {fn: i for i, fn in enumerate(footprints)}
    defects = sorted(
        defects,
        key=lambda d: (min((order[f] for f in d.frames), default=1 << 30), d.centroid_xy_m[0]),
    )
    for i, d in enumerate(defects, start=1):
        d.id = i
    return defects


def point_max_depth(
    poly: Polygon, xy: np.ndarray, residual: np.ndarray, mc: MapSegmentConfig
) -> float | None:
    """Deepest point inside ``poly`` relative to the median road level in a ring around it.

    The deepest depth at least ``POINT_SUPPORT`` points reach (``supported_max``): an isolated
    deepest point (deeper than the next by more than max(5 mm, 20 %)) is taken for a mismatch
    and the next one is used, and so on. None with fewer than ``min_support_points`` inside.
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
    return supported_max(level - r[ins], POINT_SUPPORT)


def pair_max_depth(
    poly: Polygon, pair_pts: list[tuple[np.ndarray, np.ndarray]], mc: MapSegmentConfig
) -> float | None:
    """Max depth of the defect inside ``poly`` measured in each pair's OWN frame.

    Each pair whose points cover the outline: a robust plane through its road points in a ring
    (``level_ring_m`` wide) around the outline, and the deepest depth at least
    ``POINT_SUPPORT`` of its points inside reach (``supported_max``). The pairs that see most
    of the defect (at least 80 % of the best pair's points inside) are combined by their
    median. A pair's relative geometry is accurate to ~2 mm, while the fused map's trajectory
    error shifts the walls.
    None when no pair has ``min_support_points`` inside and a ring of road points.
    """
    from shapely import contains_xy

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
        plane = robust_plane_z(Q[ring])
        if plane is None:
            continue
        # The deepest point that another point corroborates: the points sample a pothole's
        # bottom sparsely, so lower percentiles under-read it (bench: 2nd-deepest 4.4 mm MAE vs
        # 3.5 mm), but one mismatch must not set it (with two or three pairs the median over
        # pairs would keep it); a mismatch in several pairs is voted out by the median.
        d = supported_max(-plane_signed_distance(Q[ins], plane), POINT_SUPPORT)
        if d is not None:
            est.append((int(ins.sum()), d))
    if not est:
        return None
    n_best = max(n for n, _ in est)
    return float(np.median([v for n, v in est if n >= 0.8 * n_best]))
