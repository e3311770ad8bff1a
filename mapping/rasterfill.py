"""Fills of the dense surface's empty cells (``mapping.rasterise``): holes inside the measured
surface from the cells at their own edge (``fill_inward``), and the cells one frame only saw
(``single_view_heights``). Pure functions on (H, W) float32 arrays of heights (m, NaN =
unknown)."""

from __future__ import annotations

import math

import cv2
import numpy as np


def fill_inward(
    values: np.ndarray, max_px: float, max_spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """Fill the NaN cells of (H, W) ``values`` within ``max_px`` cells (L2) of finite ones ring
    by ring from the border of the measured cells inwards, each ring with the mean of its
    already known 8-neighbours: a hole continues the cells at its own edge, where a wide
    smoothing kernel would mix in the road around a pothole and read its floor shallow. A cell
    whose known neighbours span more than ``max_spread`` (a step such as a pothole wall, where
    the hole's value is unknown by that much) stays NaN and fills nothing further.

    Returns the float32 filled copy and the (H, W) bool mask of the cells within ``max_px`` of
    the measured ones (filled or not): the holes the measured surface itself answers for."""
    out = np.asarray(values, np.float32).copy()
    known = np.isfinite(out)
    if max_px <= 0 or known.all() or not known.any():
        return out, known.copy()
    dist = cv2.distanceTransform((~known).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    near = dist <= max_px
    todo = ~known & near
    k3 = (3, 3)
    ones = np.ones(k3, np.uint8)
    for _ in range(int(math.ceil(max_px)) + 1):
        if not todo.any():
            break
        v0 = np.where(known, out, 0).astype(np.float32)
        ssum = cv2.boxFilter(v0, -1, k3, normalize=False, borderType=cv2.BORDER_CONSTANT)
        cnt = cv2.boxFilter(
            known.astype(np.float32), -1, k3, normalize=False, borderType=cv2.BORDER_CONSTANT
        )
        hi = cv2.dilate(np.where(known, out, -np.inf).astype(np.float32), ones)
        lo = cv2.erode(np.where(known, out, np.inf).astype(np.float32), ones)
        ring = todo & (cnt > 0)
        if not ring.any():
            break
        with np.errstate(invalid="ignore", over="ignore"):
            ok = ring & (hi - lo <= max_spread)
        out[ok] = ssum[ok] / cnt[ok]
        known |= ok
        todo &= ~ring
    return out, near


# half-side of the block of cells whose median judges a known cell as road or relief for the
# single-view fill (cells; 2 = 5 x 5): a pothole reaching the measured part's edge spans more
# than that and its cells agree, while one noisy edge cell (matched with half a window, σ
# 2-3 mm: more than the relief limit) is outvoted by its neighbours
RELIEF_BLOCK_HALF = 2


def single_view_heights(
    values: np.ndarray, cells: np.ndarray, near_px: float, road_m: float
) -> np.ndarray:
    """Heights for the (H, W) bool ``cells`` of ``values`` (NaN there) that one frame only saw:
    the road model, 0, except where the nearest known value within ``near_px`` cells is relief:
    NaN, unknown. A known cell is relief when the median of the known values in the
    (2 ``RELIEF_BLOCK_HALF`` + 1)² block around it is (|median| > ``road_m``). A strip between
    two pairs' parts (seen once where a faster drive's frames overlap by less than half) that
    crosses a pothole stays unknown: the road model there split it into a defect per pair, and
    its depth continued joined two potholes into one. Judged on one cell, a noisy cell at the
    measured part's edge blanked a wedge of road behind it (tilted 45° drive: 0.2 % of the
    corridor). Returns the (K,) float32 values of ``cells`` in row-major order."""
    known = np.isfinite(values)
    out = np.zeros(int(cells.sum()), np.float32)
    if near_px <= 0 or not known.any():
        return out
    dist, lab = cv2.distanceTransformWithLabels(
        (~known).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    near = dist[cells] <= near_px
    nearest = lab[cells][near] - 1  # labels number the known cells in row-major order, from 1
    used, inv = np.unique(nearest, return_inverse=True)
    iy, ix = np.divmod(np.flatnonzero(known)[used], values.shape[1])
    r = RELIEF_BLOCK_HALF
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    h, w = values.shape
    yy = iy[:, None] + dy.ravel()[None, :]
    xx = ix[:, None] + dx.ravel()[None, :]
    inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
    # NaN where unknown or beyond the tile (a clipped index would count an edge cell again);
    # the cell itself is known and inside
    block = np.where(inside, values[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)], np.nan)
    relief = np.abs(np.nanmedian(block, axis=1)) > road_m
    out[np.flatnonzero(near)[relief[inv]]] = np.nan
    return out
