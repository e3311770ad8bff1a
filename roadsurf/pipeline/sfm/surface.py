"""The SfM baseline's road surface: residuals to a local robust surface, and the mean raster.

Small local versions for a sparse cloud on one grid; the mapping stage has its own dense, tiled
ones (roadsurf.mapping.surface, roadsurf.mapping.raster), which bin and fit differently.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.core.geometry import check_shape
from roadsurf.io.formats import LOCAL_CRS, GridSpec
from roadsurf.pipeline.sfm.config import SfmBaselineConfig

if TYPE_CHECKING:
    from roadsurf.pipeline.sfm.georef import ModelGeo

log = logging.getLogger(__name__)


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
            sig = MAD_TO_SIGMA * float(np.median(np.abs(r[w]))) + 1e-6
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
) -> tuple[np.ndarray, GridSpec]:
    """Mean of ``values`` per cell of a north-up grid covering ``xy`` (N, 2) metres.

    Returns (float32 (H, W) raster, NaN where no point fell, GridSpec). The GSD is coarsened
    when the bounding grid would exceed ``max_px`` pixels."""
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


def road_points(
    parts: list[ModelGeo], cfg: SfmBaselineConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The placed models' points near a camera and on the road: (p_w (K, 3) m, rgb (K, 3) uint8,
    residual_m (K,) to the local road surface).

    Per model: each model has its own small vertical tilt/offset error, so the local road
    surface is fitted to one model's points at a time (mixing layers would corrupt it)."""
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
    return p_w, rgb, residual
