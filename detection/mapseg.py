"""Defects on the global map: segment the residual surface raster, cluster with mean shift,
measure each defect (outline, depth, area, volume, length, width, type, severity, confidence).

The raster is ``RUN/surface.tif`` (residual height, m, negative below the road) when mapping
wrote it; otherwise the stage rasterises the points it has (``RUN/map_points.npz`` or the pairs
placed with the trajectory). Thresholds are floors raised to multiples of the raster's measured
noise σ (1.4826 · MAD over the observed cells, which are mostly flat road).

Segmentation is hysteresis thresholding: seed cells deeper than T_d, outlines where the surface
is deeper than a rim threshold near the noise floor, so the outline follows the defect's rim
rather than the T_d contour (a bowl cut at T_d would lose a third of its area).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy import ndimage
from scipy.cluster.hierarchy import DisjointSet

from roadsurf.core.fits import robust_sigma
from roadsurf.detection.config import MapSegmentConfig, SeverityConfig
from roadsurf.detection.mapbridge import bridged_components
from roadsurf.detection.meanshift import mean_shift_flat
from roadsurf.detection.planefit import nanmedian_last
from roadsurf.detection.robust import CELL_SUPPORT, supported_max
from roadsurf.io.formats import GridSpec

if TYPE_CHECKING:
    from roadsurf.detection.rutrecord import RutTrace

log = logging.getLogger(__name__)


@dataclass
class Surface:
    """Residual raster in the grid frame: (H, W) float32 metres, NaN where unobserved."""

    residual_m: np.ndarray
    grid: GridSpec
    source: str  # "surface.tif" | "map_points.npz" | "pairs"
    # (H, W) σ of each cell's height (m; the dense surface's surface_sigma), NaN or None where
    # unknown: a seed must also be deeper than noise_k x its own cell's σ
    sigma_m: np.ndarray | None = None
    # (H, W) pairs' samples fused into each cell (the dense surface's surface_nobs) or None:
    # with it, a seed must be a measured cell (count >= 1), not a fill
    count: np.ndarray | None = None


@dataclass
class Region:
    """One defect's cells before it becomes a ``Defect``."""

    rows: np.ndarray  # (K,) int raster rows
    cols: np.ndarray  # (K,) int raster cols
    depth_m: np.ndarray  # (K,) depth (positive down) from the raw raster, NaN where unobserved
    depth_smooth_m: np.ndarray  # (K,) depth of the smoothed raster
    support_pairs: set[int] = field(default_factory=set)  # pairs whose refined points fall in it
    n_support_points: int = 0
    support_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # evidence ids
    noise_m: float = float("nan")  # σ of the raster window it was segmented in (m)
    seed_m: float = float("nan")  # T_d used in that window (m)
    rut: RutTrace | None = None  # set when the region is a traced rut (``ruts``)
    # area of its cells deeper than T_d measured alike by >= 2 pairs of the dense surface (m²)
    dense_support_m2: float = 0.0


@dataclass
class Measured:
    """Measurements of one region (grid frame metres)."""

    outline_xy_m: np.ndarray  # (K, 2) exterior ring, not closed
    centroid_xy_m: np.ndarray  # (2,)
    max_depth_m: float
    mean_depth_m: float
    area_m2: float
    volume_m3: float
    length_m: float
    width_m: float
    deep_xy_m: np.ndarray  # (M, 2) centres of cells deeper than the frame-label depth


def smooth_nan(a: np.ndarray, sigma_px: float, min_support: float = 0.05) -> np.ndarray:
    """Gaussian smoothing that ignores NaN cells (normalised convolution).

    Unobserved cells with enough observed neighbours (kernel weight >= ``min_support``) are
    filled, so small holes inside a defect do not read as zero depth; the rest stay NaN.
    """
    valid = np.isfinite(a)
    if sigma_px <= 0:
        return a.copy()
    num = ndimage.gaussian_filter(np.where(valid, a, 0).astype(np.float32), sigma_px)
    den = ndimage.gaussian_filter(valid.astype(np.float32), sigma_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    out[den < min_support] = np.nan
    return out


def road_level(
    res: np.ndarray, exclude: np.ndarray, gsd_m: float, window_m: float, block_m: float = 0.05
) -> np.ndarray:
    """Slowly varying road level (H, W) of a residual raster: median of 5 cm blocks (excluded
    cells left out), then a median over ``window_m``; NaN blocks take the nearest value."""
    b = max(1, int(round(block_m / gsd_m)))
    h, w = res.shape
    hb, wb = -(-h // b), -(-w // b)
    a = np.full((hb * b, wb * b), np.nan, np.float32)
    a[:h, :w] = np.where(exclude, np.nan, res)
    blocks = a.reshape(hb, b, wb, b).transpose(0, 2, 1, 3).reshape(hb, wb, b * b)
    med = nanmedian_last(blocks)
    k = max(3, int(round(window_m / block_m)) | 1)
    # k x k median ignoring NaN, edges repeated (ndimage's mode="nearest"), vectorised
    win = np.lib.stride_tricks.sliding_window_view(np.pad(med, k // 2, mode="edge"), (k, k))
    lvl = nanmedian_last(win.reshape(*med.shape, k * k))
    bad = ~np.isfinite(lvl)
    if bad.all():
        return np.zeros_like(res)
    if bad.any():
        idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
        lvl = lvl[tuple(idx)]
    up = np.repeat(np.repeat(lvl, b, axis=0), b, axis=1)[:h, :w]
    return cv2.blur(up.astype(np.float32), (b | 1, b | 1))


def _near_seeds(seed: np.ndarray, gsd_m: float, frac: float, min_m: float) -> np.ndarray:
    """Cells within max(min_m, frac · r_eq) of a seed component (r_eq: its equivalent radius)."""
    if not seed.any():
        return np.zeros_like(seed)
    lab, n = ndimage.label(seed, structure=np.ones((3, 3), bool))
    area = np.bincount(lab.ravel(), minlength=n + 1).astype(float)
    reach_px = np.maximum(min_m / gsd_m, frac * np.sqrt(area / np.pi))
    dist, idx = ndimage.distance_transform_edt(~seed, return_indices=True)
    nearest = lab[idx[0], idx[1]]
    return dist <= reach_px[nearest]


def choose_gsd(xy_m: np.ndarray, gsd_min_m: float, gsd_max_m: float = 0.1) -> float:
    """Finest cell size at which occupied cells hold >= 2 points on average (about 80 % of the
    covered cells then hold a point), for rasterising a sparse cloud."""
    xy = np.asarray(xy_m, float)
    if len(xy) < 2:
        return gsd_min_m
    xy = xy - xy.min(axis=0)
    g = gsd_min_m
    while g < gsd_max_m:
        cells = np.floor(xy / g).astype(np.int64)
        n_occ = len(np.unique(cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1]))
        if len(xy) / n_occ >= 2.0:
            break
        g *= 1.25
    return float(min(g, gsd_max_m))


@dataclass
class Segmentation:
    noise_m: float  # σ of the residual surface (robust)
    seed_m: float  # T_d on the map
    rim_m: float  # outline threshold
    regions: list[Region]
    grid: GridSpec  # grid of the regions' rows/cols (the residual's, cropped to the data)


def seed_cells(
    depth: np.ndarray,
    seed_t: float,
    cell_sigma: np.ndarray | None,
    count: np.ndarray | None,
    noise_k: float,
) -> np.ndarray:
    """(H, W) bool: the seed test of ``segment`` on depths (m, positive below the road) with
    the threshold ``seed_t`` (T_d = max(T_d floor, noise_k σ of the window)). With the dense
    surface's ``cell_sigma`` also deeper than ``noise_k`` x the cell's own σ (NaN: no test): a
    steep camera's far field (σ 13-67 mm at 55°) read 17-180 mm "defects" against a window σ
    of 1-2 mm, the true potholes' cells read 1-3 mm. With its ``count`` also a measured cell:
    there the dense matching failed, the sparse points' fill reads a steep camera's far field
    decimetres off (55° at 640 x 480: 80-99 % of the false regions' cells were fills); a
    hole-filled wall still joins its floor's seeds through the outline."""
    seed = depth >= seed_t
    if cell_sigma is not None:
        seed &= depth >= noise_k * np.nan_to_num(cell_sigma, nan=0.0)
    if count is not None:
        seed &= count >= 1
    return seed


def _joined(
    lab: np.ndarray,
    objects: list,
    a: int,
    b: int,
    gap_px: float,
    depth: np.ndarray,
    unknown: np.ndarray,
    road_m: float,
) -> bool:
    """True when components a and b of ``lab`` are parts of one defect: cells at most
    ``gap_px`` apart, one inside the other's outline, or the road between their nearest cells
    is not road level (its median ``depth`` at least ``road_m`` below the road, or mostly
    ``unknown``): one pothole's floor that noise cut, where two potholes have measured road
    between them."""
    sa, sb = objects[a - 1], objects[b - 1]
    if sa is None or sb is None:
        return False
    r0, c0 = min(sa[0].start, sb[0].start), min(sa[1].start, sb[1].start)
    r1, c1 = max(sa[0].stop, sb[0].stop), max(sa[1].stop, sb[1].stop)
    win = lab[r0:r1, c0:c1]
    dist, (ir, ic) = ndimage.distance_transform_edt(win != a, return_indices=True)
    rb, cb = np.nonzero(win == b)
    k = int(np.argmin(dist[rb, cb]))
    if dist[rb[k], cb[k]] <= gap_px + 1.0:
        return True
    # one inside the other's outline (a floor fragment within its wall's ring): one defect
    if ndimage.binary_fill_holes(win == a)[rb, cb].any():
        return True
    ra, ca = np.nonzero(win == a)
    if ndimage.binary_fill_holes(win == b)[ra, ca].any():
        return True
    # the cells on the line between the nearest two, outside both components
    p, q = np.array([ir[rb[k], cb[k]], ic[rb[k], cb[k]]]), np.array([rb[k], cb[k]])
    n = int(np.ceil(np.hypot(*(q - p)))) + 1
    rr = np.round(np.linspace(p[0], q[0], n)).astype(int)
    cc = np.round(np.linspace(p[1], q[1], n)).astype(int)
    between = (win[rr, cc] != a) & (win[rr, cc] != b)
    if not between.any():
        return True
    rr, cc = rr[between] + r0, cc[between] + c0
    unk = unknown[rr, cc]
    if unk.mean() >= 0.5:
        return True
    return bool(np.median(depth[rr[~unk], cc[~unk]]) >= road_m)


def segment(
    surface: Surface,
    cfg: MapSegmentConfig,
    evidence_xy_m: np.ndarray | None = None,
    evidence_pair: np.ndarray | None = None,
) -> Segmentation:
    """Hysteresis segmentation + flat-kernel mean shift on the residual raster.

    evidence_xy_m: (N, 2) refined defect points from the pairs in the grid frame; evidence_pair:
    (N,) int pair id of each. They join the mean-shift points (so defects seen in pieces by
    several pairs are clustered together) and give each region its 3D support.
    """
    box = surface.grid.crop_to(np.isfinite(surface.residual_m), 4)
    res, grid = surface.residual_m.astype(np.float32), surface.grid
    cell_sigma, count = surface.sigma_m, surface.count
    if box is not None:
        rs, cs, grid = box
        res = res[rs, cs]
        cell_sigma = None if cell_sigma is None else cell_sigma[rs, cs]
        count = None if count is None else count[rs, cs]
    noise = robust_sigma(res)
    if not np.isfinite(noise):
        return Segmentation(float("nan"), float("nan"), float("nan"), [], grid)
    # Fill small holes from observed neighbours, then smooth lightly (σ in metres).
    res = np.where(np.isfinite(res), res, smooth_nan(res, cfg.fill_px))
    unknown = ~np.isfinite(res)
    if cfg.level_window_m > 0:
        # Re-level: the residual of a real map drifts by millimetres around zero (seams, local
        # fits); measure depth from the surrounding road instead. Deep cells are left out.
        sm0 = smooth_nan(res, cfg.smooth_m / grid.gsd_m, min_support=0.5)
        deep0 = sm0 <= -max(cfg.depth_threshold_m, cfg.noise_k * noise)
        res = res - road_level(res, deep0, grid.gsd_m, cfg.level_window_m)
        noise = robust_sigma(res)
    seed_t = max(cfg.depth_threshold_m, cfg.noise_k * noise)
    rim_t = max(cfg.rim_threshold_m, cfg.rim_noise_k * noise)
    sm = smooth_nan(res, cfg.smooth_m / grid.gsd_m, min_support=0.5)
    depth_s = -np.nan_to_num(sm, nan=0.0)
    seed = seed_cells(depth_s, seed_t, cell_sigma, count, cfg.noise_k)
    cell_s = None if cell_sigma is None else np.nan_to_num(cell_sigma, nan=0.0)
    # Outline mask: deeper than the rim threshold, with small unobserved holes closed, and not
    # further from the seeds than a share of their size (no leaking along shallow undulations).
    rim = depth_s >= rim_t
    if cell_s is not None:  # the outline's threshold likewise (the pairs' evidence points
        rim &= depth_s >= cfg.rim_noise_k * cell_s  # make regions of rim components too)
    rim = ndimage.binary_closing(rim, structure=np.ones((3, 3), bool)) | rim
    rim &= _near_seeds(seed, grid.gsd_m, cfg.rim_max_grow_frac, cfg.rim_max_grow_min_m)
    rim_lab, n_rim = ndimage.label(rim, structure=np.ones((3, 3), bool))
    bridge_of = bridged_components(rim, rim_lab, n_rim, unknown, cfg.bridge_unknown_m / grid.gsd_m)
    seed_rc = np.argwhere(seed)
    if len(seed_rc) == 0:
        return Segmentation(noise, seed_t, rim_t, [], grid)
    seed_xy = grid.xy_from_rowcol(seed_rc[:, 0], seed_rc[:, 1])
    seed_comp = rim_lab[seed_rc[:, 0], seed_rc[:, 1]]

    # Evidence points: inside the raster, with their rim component (0 = outside any).
    ev_xy = np.zeros((0, 2)) if evidence_xy_m is None else np.asarray(evidence_xy_m, float)
    ev_pair = np.zeros(len(ev_xy), int) if evidence_pair is None else np.asarray(evidence_pair)
    ev_comp = np.zeros(len(ev_xy), int)
    if len(ev_xy):
        rc = np.floor(grid.rowcol_from_xy(ev_xy) + 0.5).astype(int)
        inside = (
            (rc[:, 0] >= 0) & (rc[:, 0] < grid.height) & (rc[:, 1] >= 0) & (rc[:, 1] < grid.width)
        )
        r_pad = max(0, int(round(cfg.point_support_radius_m / grid.gsd_m)))
        lab_near = ndimage.grey_dilation(rim_lab, size=2 * r_pad + 1) if r_pad else rim_lab
        ev_comp[inside] = lab_near[rc[inside, 0], rc[inside, 1]]

    # Flat-kernel mean shift over seed cells and evidence points (eq. 5.11-5.12).
    pts = np.vstack([seed_xy, ev_xy])
    wts = np.concatenate([depth_s[seed_rc[:, 0], seed_rc[:, 1]], np.full(len(ev_xy), seed_t)])
    labels, _ = mean_shift_flat(
        pts,
        cfg.mean_shift_window_m,
        weights=wts,
        max_iter=cfg.mean_shift_max_iter,
        tol_m=cfg.mean_shift_tol_m,
        merge_m=0.5 * cfg.mean_shift_window_m,
    )
    comps = np.concatenate([seed_comp, ev_comp])
    objects = ndimage.find_objects(rim_lab)
    # Union-find over the rim components: those a mean-shift cluster holds are one defect when
    # they lie within join_gap_m of each other (pieces of one defect; measured road between
    # two potholes keeps them apart), and those joined across an unknown strip
    sets = DisjointSet(range(1, n_rim + 1))
    in_cluster: dict[int, set[int]] = {}
    for lab, comp in zip(labels.tolist(), comps.tolist(), strict=True):
        if comp > 0:
            in_cluster.setdefault(lab, set()).add(comp)
    gap_px = cfg.join_gap_m / grid.gsd_m
    for members in in_cluster.values():
        ms = sorted(members)
        for i, a in enumerate(ms):
            for b in ms[i + 1 :]:
                if gap_px <= 0 or _joined(
                    rim_lab, objects, a, b, gap_px, depth_s, unknown, 0.5 * rim_t
                ):
                    sets.merge(a, b)
    seen_comps = sorted({c for m in in_cluster.values() for c in m})
    first_by_bridge: dict[int, int] = {}
    for comp in seen_comps:
        sets.merge(comp, first_by_bridge.setdefault(int(bridge_of[comp]), comp))
    groups: dict[int, set[int]] = {}
    for comp in seen_comps:
        groups.setdefault(sets[comp], set()).add(comp)

    regions: list[Region] = []
    for comp_set in groups.values():
        rr, cc = [], []
        for comp in comp_set:
            sl = objects[comp - 1]
            if sl is None:
                continue
            sub = rim_lab[sl] == comp
            r, c = np.nonzero(ndimage.binary_fill_holes(sub))
            rr.append(r + sl[0].start)
            cc.append(c + sl[1].start)
        rows = np.concatenate(rr)
        cols = np.concatenate(cc)
        reg = Region(
            rows=rows,
            cols=cols,
            depth_m=-res[rows, cols].astype(float),
            depth_smooth_m=depth_s[rows, cols].astype(float),
        )
        in_reg = np.isin(ev_comp, list(comp_set)) if len(ev_comp) else np.zeros(0, bool)
        reg.support_pairs = set(np.unique(ev_pair[in_reg]).tolist())
        reg.n_support_points = int(in_reg.sum())
        reg.support_idx = np.flatnonzero(in_reg)
        reg.noise_m, reg.seed_m = noise, seed_t
        regions.append(reg)
    return Segmentation(noise, seed_t, rim_t, regions, grid)


def measure(region: Region, grid: GridSpec, frame_depth_m: float) -> Measured:
    """Outline, centroid, depths, area, volume (fill), min-area-rectangle length and width."""
    gsd = grid.gsd_m
    depth = _raw_depth(region)
    xy = grid.xy_from_rowcol(region.rows, region.cols)
    area = float(len(region.rows) * gsd * gsd)
    volume = float(depth.sum() * gsd * gsd)
    max_depth = raster_max_depth(region)
    mean_depth = float(depth.mean()) if len(depth) else 0.0
    # Outline: external contour(s) of the cell mask, pushed out by half a cell.
    r0, c0 = region.rows.min(), region.cols.min()
    mask = np.zeros((region.rows.max() - r0 + 3, region.cols.max() - c0 + 3), np.uint8)
    mask[region.rows - r0 + 1, region.cols - c0 + 1] = 1
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    ring = _outline(contours, r0 - 1, c0 - 1, grid)
    if len(region.rows) >= 3:
        # Centre first: float32 (what OpenCV takes) cannot hold UTM coordinates to a millimetre.
        (_, _), (a, b), _ = cv2.minAreaRect((xy - xy.mean(axis=0)).astype(np.float32))
        length, width = max(a, b) + gsd, min(a, b) + gsd
    else:
        length = width = gsd * max(1, len(region.rows))
    deep = region.depth_smooth_m >= frame_depth_m
    return Measured(
        outline_xy_m=ring,
        centroid_xy_m=xy.mean(axis=0),
        max_depth_m=max_depth,
        mean_depth_m=mean_depth,
        area_m2=area,
        volume_m3=volume,
        length_m=float(length),
        width_m=float(width),
        deep_xy_m=xy[deep],
    )


def _raw_depth(region: Region) -> np.ndarray:
    """(K,) depth (m, >= 0) of the region's cells on the hole-filled, unsmoothed raster (the
    smoothed depth where the raster has none)."""
    depth = np.where(np.isfinite(region.depth_m), region.depth_m, region.depth_smooth_m)
    return np.clip(np.nan_to_num(depth, nan=0.0), 0.0, None)


def raster_max_depth(region: Region) -> float:
    """The region's max depth on the raster (m): the deepest depth ``CELL_SUPPORT`` cells of
    the hole-filled, unsmoothed surface reach. The smoothing used for the thresholds would shave
    a few millimetres off the bottom of a small pothole, and one outlier point mapped into a few
    cells must not set it."""
    return float(supported_max(_raw_depth(region), CELL_SUPPORT) or 0.0)


def _outline(contours: tuple, row_off: int, col_off: int, grid: GridSpec) -> np.ndarray:
    """Contour pixels -> one exterior ring in grid metres (union of pieces, half-cell buffer)."""
    from shapely.geometry import MultiPoint, Polygon
    from shapely.ops import unary_union

    polys = []
    for c in contours:
        pc = c.reshape(-1, 2).astype(float)  # (x=col, y=row)
        xy = grid.xy_from_rowcol(pc[:, 1] + row_off, pc[:, 0] + col_off)
        if len(xy) >= 3:
            p = Polygon(xy).buffer(0)
        else:
            p = MultiPoint(xy).convex_hull
        polys.append(p.buffer(0.5 * grid.gsd_m, join_style="mitre"))
    geom = unary_union(polys)
    if geom.geom_type != "Polygon":
        geom = geom.convex_hull
    geom = geom.simplify(0.25 * grid.gsd_m)
    return np.asarray(geom.exterior.coords)[:-1]


def classify(m: Measured, cfg: MapSegmentConfig) -> str:
    """pothole | crack | rut from shape (elongation, width, length)."""
    elong = m.length_m / max(m.width_m, 1e-6)
    if elong >= cfg.elongation_min and m.width_m <= cfg.crack_max_width_m:
        return "crack"
    if elong >= cfg.elongation_min and m.length_m >= cfg.rut_min_length_m:
        return "rut"
    return "pothole"


def severity(kind: str, m: Measured, cfg: SeverityConfig) -> str:
    """ASTM D6433 pothole table (depth x mean diameter), FHWA DIM crack widths, D6433 ruts."""
    if kind == "crack":
        w = m.width_m
        return (
            "low"
            if w <= cfg.crack_width_low_m
            else "medium"
            if w <= cfg.crack_width_high_m
            else "high"
        )
    d = m.max_depth_m
    if kind == "rut":
        return (
            "low" if d <= cfg.rut_depth_low_m else "medium" if d <= cfg.rut_depth_high_m else "high"
        )
    depth_band = 0 if d <= cfg.depth_low_m else 1 if d <= cfg.depth_high_m else 2
    diam = 0.5 * (m.length_m + m.width_m)
    diam_band = 0 if diam <= cfg.diameter_small_m else 1 if diam <= cfg.diameter_large_m else 2
    table = (
        ("low", "low", "medium"),  # depth <= 25 mm
        ("low", "medium", "high"),  # 25-50 mm
        ("medium", "medium", "high"),  # > 50 mm
    )
    return table[depth_band][diam_band]
