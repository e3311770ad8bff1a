"""The SfM baseline's road surface: residuals to the product's local road surface
(``mapping.surface.LocalSurface``) and the mean raster on the grid of ``roadsurf run``
(``mapping.raster``); the settings are the baseline's own, for a sparse cloud.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.geometry import check_shape
from roadsurf.io.formats import LOCAL_CRS, GridSpec
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.raster import corridor_tiles, grid_mean
from roadsurf.mapping.surface import LocalSurface
from roadsurf.pipeline.sfm.config import SfmBaselineConfig

if TYPE_CHECKING:
    from roadsurf.pipeline.sfm.georef import ModelGeo

log = logging.getLogger(__name__)


def surface_raster(
    xy: np.ndarray, values: np.ndarray, cfg: SfmBaselineConfig, crs: str | None
) -> tuple[np.ndarray, GridSpec]:
    """Mean of ``values`` per cell (``mapping.raster.grid_mean``) of the grid ``roadsurf run``
    writes surface.tif on: the tile lattice of ``mapping.raster.corridor_tiles`` (origin on
    multiples of ``tile_px`` x GSD) around the (N, 2) grid-CRS points ``xy`` (m), so with the
    same ``gsd_m`` and ``tile_px`` the two rasters coincide cell for cell. The GSD is doubled
    until the grid has at most ``max_raster_px`` pixels (or is one tile). Returns (float32 (H, W), NaN where no
    point fell, its GridSpec)."""
    xy = check_shape("xy", xy, (None, 2))
    gsd = cfg.gsd_m
    while True:
        lat = corridor_tiles(xy, crs or LOCAL_CRS, gsd, cfg.tile_px)[0]
        grid = lat.full_grid
        if grid.width * grid.height <= cfg.max_raster_px or lat.n_rows * lat.n_cols == 1:
            break  # (one tile is the smallest grid there is)
        gsd *= 2
    if gsd != cfg.gsd_m:
        log.warning(
            "surface raster: GSD coarsened from %.3f m to %.3f m (size cap)", cfg.gsd_m, gsd
        )
    return grid_mean(xy, values, grid), grid


def local_surface(cfg: SfmBaselineConfig, xyz_m: np.ndarray) -> LocalSurface:
    """The product's local road surface (``mapping.surface.LocalSurface``) fitted to a model's
    (N, 3) points (m), with the SfM baseline's lattice, window and inlier settings: the sparse
    cloud needs wider windows than the product's dense one (a node needs 8 points)."""
    mcfg = replace(
        MappingConfig(),
        local_fit_cell_m=cfg.local_fit_cell_m,
        local_fit_window_m=cfg.local_fit_window_m,
        local_fit_inlier_m=cfg.local_fit_inlier_m,
        local_fit_bridge_m=0.0,  # the baseline keeps the surface it was measured with
    )
    return LocalSurface(mcfg, xyz_m, progress=False)


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
        res_k = local_surface(cfg, g2.p_w[near]).residual(g2.p_w[near])
        fitted = np.abs(np.nan_to_num(res_k, nan=np.inf)) <= cfg.max_abs_residual_m
        pw_l.append(g2.p_w[near][fitted])
        rgb_l.append(g2.rgb[near][fitted])
        res_l.append(res_k[fitted])
    p_w = np.concatenate(pw_l)
    rgb = np.concatenate(rgb_l)
    residual = np.concatenate(res_l)
    return p_w, rgb, residual
