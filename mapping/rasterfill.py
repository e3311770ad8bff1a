"""Fills of the dense surface's empty cells (``mapping.rasterise``): holes inside the measured
surface from the cells at their own edge (``fill_inward``), and the cells one frame only saw
(``single_view_heights``). Pure functions on (H, W) float32 arrays of heights (m, NaN =
unknown)."""

from __future__ import annotations

import math

import cv2
import numpy as np

# the largest hole (cells) solved as a ramp (``fill_inward``): a 12 cm wall band around a
# 40 cm pothole at 2 mm cells is ~10,000
MAX_RAMP_CELLS = 40_000


def fill_inward(
    values: np.ndarray, max_px: float, max_spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """Fill the NaN cells of (H, W) ``values`` within ``max_px`` cells (L2) of finite ones ring
    by ring from the border of the measured cells inwards, each ring with the mean of its
    already known 8-neighbours: a hole continues the cells at its own edge, where a wide
    smoothing kernel would mix in the road around a pothole and read its floor shallow.

    A hole whose rings meet across a step (a cell whose known neighbours span more than
    ``max_spread``: the band of a pothole wall the matching left empty, the rim on one side,
    the floor on the other) is filled instead by harmonic interpolation between its edges
    (``_harmonic_fill``): a ramp from rim to floor. Where the band is occluded, every ray that
    passed over it reached the floor beyond, so the true surface lies at or below that ramp;
    the flat continuation put the step in the band's middle and cut a small deep pothole's
    area by 19-55 % (session 33's battery).

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
    holes = near & ~np.isfinite(np.asarray(values, np.float32))
    # a step: a cell left empty, or two filled cells side by side whose rings came from
    # either side of it (an even band's fronts meet without an empty cell between them)
    f = np.where(holes & known, out, np.nan).astype(np.float32)
    hi = cv2.dilate(np.where(np.isfinite(f), f, -np.inf).astype(np.float32), ones)
    lo = cv2.erode(np.where(np.isfinite(f), f, np.inf).astype(np.float32), ones)
    with np.errstate(invalid="ignore", over="ignore"):
        blocked = holes & (~known | (hi - lo > max_spread))
    if blocked.any():
        n_lab, lab = cv2.connectedComponents(holes.astype(np.uint8), connectivity=8)
        steps = np.zeros(n_lab, bool)
        steps[np.unique(lab[blocked])] = True
        # a wall's band is thousands of cells; a component beyond this is a fragmented
        # tile's web of holes (a sparse solve of seconds and a GB), left to the ring fill
        steps &= np.bincount(lab.ravel(), minlength=n_lab) <= MAX_RAMP_CELLS
        steps[0] = False  # label 0: not a hole
        cells = steps[lab] & holes
        out[cells] = _harmonic_fill(np.where(cells, np.nan, out), cells)
    return out, near


def _harmonic_fill(values: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Harmonic interpolation of the (H, W) bool ``cells`` of ``values`` (finite cells are
    fixed, NaN cells outside ``cells`` are left out): each cell the mean of its 8 neighbours
    that are finite or in ``cells``, solved as one sparse system. Between two levels it is a
    ramp; it never leaves the range of the edge values (the maximum principle). Returns the
    (K,) float32 values of ``cells`` in row-major order; NaN for a component with no finite
    neighbour."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.linalg import spsolve

    h, w = values.shape
    iy, ix = np.nonzero(cells)
    k = iy.size
    index = np.full((h, w), -1, np.int64)
    index[iy, ix] = np.arange(k)
    rows, cols, diag = [], [], np.zeros(k)
    rhs = np.zeros(k)
    touch = np.zeros(k, bool)  # a cell with a fixed neighbour
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            y, x = iy + dy, ix + dx
            inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
            yc, xc = np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)
            v = values[yc, xc]
            fixed = inside & np.isfinite(v)
            free = inside & (index[yc, xc] >= 0)
            diag += fixed | free
            rhs[fixed] += v[fixed]
            touch |= fixed
            rows.append(np.flatnonzero(free))
            cols.append(index[yc, xc][free])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    idx = np.arange(k)
    a = csr_matrix(
        (
            np.concatenate([diag, -np.ones(r.size)]),
            (np.concatenate([idx, r]), np.concatenate([idx, c])),
        ),
        shape=(k, k),
    )
    # a component with no fixed neighbour is singular: it stays NaN
    n_lab, lab = cv2.connectedComponents(cells.astype(np.uint8), connectivity=8)
    anchored = np.zeros(n_lab, bool)
    anchored[lab[iy, ix][touch]] = True
    ok = anchored[lab[iy, ix]]
    out = np.full(k, np.nan, np.float32)
    if ok.any():
        sel = np.flatnonzero(ok)
        sol = spsolve(a[sel][:, sel].tocsc(), rhs[sel])
        out[sel] = np.asarray(sol, np.float32)
    return out


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
