"""Seeds for detection windows from the dense surface itself, where the pairs left no sparse
evidence (``MapSegmentConfig.raster_seeds``).

The windows of ``detection.windows`` open around the pairs' deep sparse points. A pothole whose
floor gives the feature detector nothing (a floor in the walls' shadow under a low sun: 0 deep
points where a lit one gave 9) is then never looked at, although the dense surface measured it
(a 34 mm pothole, 286 measured cells deeper than 8 mm, not reported). This scan reads the
dense rasters block by block over the mapped area and returns one seed per group of measured
cells that pass segmentation's own seed test (deeper than T_d, than ``noise_k`` x the block's
noise and than ``noise_k`` x the cell's own σ) over at least ``min_area_m2``. The window then
decides as for any other: segmentation, measurement and the 3D veto are unchanged.

Pure function of the source (memory: one block of the three rasters at a time).
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from roadsurf.core.fits import robust_sigma
from roadsurf.detection.config import MapSegmentConfig
from roadsurf.detection.mapseg import seed_cells

if TYPE_CHECKING:
    from shapely.geometry.base import BaseGeometry

    from roadsurf.detection.windows import WindowSource
    from roadsurf.io.formats import GridSpec

log = logging.getLogger(__name__)

BLOCK_PX = 1024  # cells per block side read at once


def raster_seeds(
    source: WindowSource, cfg: MapSegmentConfig, observed: BaseGeometry | None = None
) -> np.ndarray:
    """(N, 2) grid xy (m) of the centroids of the measured deep cell groups (module docstring);
    empty without the dense surface's counts (a sparse raster's cells are interpolations)."""
    grid = source.grid
    out: list[np.ndarray] = []
    if source.read_count(0, 0, 1, 1) is None:  # no counts: a sparse surface
        return np.zeros((0, 2))
    t0 = time.perf_counter()
    cell_m2 = grid.gsd_m**2
    min_cells = max(1, int(np.ceil(cfg.min_area_m2 / cell_m2)))
    n_blocks = 0
    for r0 in range(0, grid.height, BLOCK_PX):
        for c0 in range(0, grid.width, BLOCK_PX):
            h, w = min(BLOCK_PX, grid.height - r0), min(BLOCK_PX, grid.width - c0)
            if observed is not None and not _touches(grid, r0, c0, h, w, observed):
                continue
            res = source.read(r0, c0, h, w)
            fin = np.isfinite(res)
            if fin.sum() < min_cells:
                continue
            n_blocks += 1
            count = source.read_count(r0, c0, h, w)
            sig = source.read_sigma(r0, c0, h, w)
            t = max(cfg.depth_threshold_m, cfg.noise_k * robust_sigma(res[fin]))
            deep = fin & seed_cells(-np.nan_to_num(res, nan=0.0), t, sig, count, cfg.noise_k)
            if deep.sum() < min_cells:
                continue
            lab, n = ndimage.label(deep, structure=np.ones((3, 3), bool))
            sizes = np.bincount(lab.ravel(), minlength=n + 1)[1:]
            keep = np.flatnonzero(sizes >= min_cells) + 1
            if not len(keep):
                continue
            rc = np.array(ndimage.center_of_mass(deep, lab, keep), float).reshape(-1, 2)
            out.append(grid.xy_from_rowcol(rc[:, 0] + r0, rc[:, 1] + c0))
    seeds = np.concatenate(out) if out else np.zeros((0, 2))
    log.info(
        "detection: %d seed(s) from the dense surface's measured deep cells (%d block(s), %.2f s)",
        len(seeds), n_blocks, time.perf_counter() - t0,
    )  # fmt: skip
    return seeds


def _touches(grid: GridSpec, r0: int, c0: int, h: int, w: int, observed: BaseGeometry) -> bool:
    from shapely.geometry import box

    (x0, y0), (x1, y1) = grid.xy_from_rowcol(np.array([r0, r0 + h]), np.array([c0, c0 + w]))
    return bool(observed.intersects(box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))))
