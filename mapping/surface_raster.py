"""The residual surface raster of one tile: interpolation of the fused points, noise-adaptive
smoothing, and the capped fill inside the part of the road seen by both frames of an ok pair."""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.io.formats import GridSpec
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.raster import GridToEnu, fill_nodata_capped, interpolate_to_grid
from roadsurf.mapping.surface import LocalSurface
from roadsurf.mapping.types import Trajectory


def _masked_gauss(r: np.ndarray, m: np.ndarray, sig_px: float) -> np.ndarray:
    num = cv2.GaussianBlur(np.where(m, r, 0).astype(np.float32), (0, 0), sig_px)
    den = cv2.GaussianBlur(m.astype(np.float32), (0, 0), sig_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(m & (den > 1e-3), num / den, np.nan).astype(np.float32)


def surface_pad_m(cfg: MappingConfig) -> float:
    """Context (m) the surface of a tile needs around it: the coarse smoothing kernel (3σ) and
    the capped fill (its reach plus its kernel), so tile borders stay seamless."""
    fill = max(cfg.surface_fill_max_m, 0.0)
    return max(3 * max(cfg.surface_smooth_flat_m, cfg.surface_smooth_m), 2.5 * fill)


def surface_tile_filled(
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
    pad = int(math.ceil(surface_pad_m(cfg) / g)) if (sig_c > 0 or fill_px > 0) else 0
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


def two_view_mask(
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
        u, v = cam.project(X @ Wi[:3, :3])
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


def points_in(xy: np.ndarray, grid: GridSpec, margin: float) -> np.ndarray:
    x0, y1 = grid.x0_m - margin, grid.y0_m + margin
    x1, y0 = (
        grid.x0_m + grid.width * grid.gsd_m + margin,
        grid.y0_m - grid.height * grid.gsd_m - margin,
    )
    return (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
