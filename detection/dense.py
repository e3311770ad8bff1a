"""Dense measurement of a candidate defect in one pair's own frame.

The reconstruction's sparse features rarely fall on a pothole's deepest spot (dark, smooth
floors hold few features), so depths measured from them read shallow. Inside each candidate
defect this module tracks a dense grid of pixels of image a into image b with pyramidal
Lucas-Kanade, initialised by the pair's road homography H, keeps forward-backward consistent
tracks that also agree with the pair's epipolar geometry, triangulates them with the pair's
metric R, t and K, and measures the defect against a robust plane through the dense road points
in a ring around it. Work is bounded by the defects, not the image: only the pixels inside a
candidate's outline (plus its ring) are tracked.

Thresholds are relative to the measured noise of each pair's dense points (forward-backward
error, epipolar residual, plane residual), so no setting is tied to one render.

One pair's tracks: ``densepair`` (checked by ``densecheck``); here the pairs that see a defect
are combined on one cell grid and the defect is measured on it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.parallel import ordered_map
from roadsurf.detection.config import DenseConfig
from roadsurf.detection.densepair import PairDense, measure_dense
from roadsurf.detection.planefit import nanmedian_last
from roadsurf.detection.robust import DENSE_SUPPORT, SUPPORT_TOL_M, supported_max
from roadsurf.io.drive import Drive, GrayFrames
from roadsurf.reconstruction.types import PairResult

if TYPE_CHECKING:
    from shapely.geometry import Polygon

log = logging.getLogger(__name__)


@dataclass
class DenseMeasure:
    """A defect measured from the dense points of all pairs that see it (metres)."""

    max_depth_m: float  # deepest depth DENSE_SUPPORT cells of the 3 x 3 median grid reach
    mean_depth_m: float  # mean depth of the cells deeper than the rim threshold
    area_m2: float  # area of the cells deeper than the rim threshold
    volume_m3: float  # fill volume: depth summed over the cells inside the outline x cell area
    noise_m: float  # σ of the dense road points about their planes (median over pairs, m)
    coverage: float  # share of the outline's cells with a dense depth (0-1)
    n_pairs: int  # pairs that contributed
    origin_m: np.ndarray  # (2,) grid-frame xy of the dense grid's lower-left corner
    cell_m: float  # dense grid cell size (m)
    depth_grid_m: np.ndarray  # (ny, nx) combined depth per cell, NaN where no pair tracked it

    def area_deeper(self, t_m: float) -> float:
        """Area (m²) of the cells deeper than ``t_m``, untracked cells counted at the share of
        the tracked ones (as ``area_m2``)."""
        deep = np.nan_to_num(self.depth_grid_m, nan=-np.inf) >= t_m
        return float(deep.sum()) * self.cell_m**2 / max(self.coverage, 1e-6)

    def depth_at(self, xy_m: np.ndarray) -> np.ndarray:
        """(N,) dense depth (m) of the cells holding grid-frame points (N, 2); NaN outside."""
        xy = np.asarray(xy_m, float).reshape(-1, 2)
        ny, nx = self.depth_grid_m.shape
        ix = np.floor((xy[:, 0] - self.origin_m[0]) / self.cell_m).astype(int)
        iy = np.floor((xy[:, 1] - self.origin_m[1]) / self.cell_m).astype(int)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        out = np.full(len(xy), np.nan)
        out[ok] = self.depth_grid_m[iy[ok], ix[ok]]
        return out


def combine_dense(
    poly: Polygon,
    got: list[PairDense],
    *,
    edge_m: float,
    rim_k: float,
    rim_floor_m: float,
    extrapolate: bool = True,
) -> DenseMeasure | None:
    """Grid the pairs' dense depths on one cell grid (one pair's mean per cell, then the median
    over the pairs that saw the cell, without a pair's reading the others do not support:
    ``_drop_unsupported``) and measure the defect on it: the deepest depth that
    ``DENSE_SUPPORT`` cells of the 3 x 3 median reach (``supported_max``: neither one bad track
    nor one bad cell can set it), the area and mean depth of the cells deeper than the
    rim (max(rim floor, rim_k σ)), the fill volume. A defect no single pair saw whole is
    measured whole from the pairs that saw its parts."""
    from shapely import contains_xy

    if not got:
        return None
    c = max(p.spacing_m for p in got)
    core = poly.buffer(edge_m)
    x0, y0, x1, y1 = core.bounds
    nx, ny = int(np.ceil((x1 - x0) / c)) + 1, int(np.ceil((y1 - y0) / c)) + 1
    vals: list[np.ndarray] = []
    for p in got:
        ix = np.clip(((p.xy_m[:, 0] - x0) / c).astype(int), 0, nx - 1)
        iy = np.clip(((p.xy_m[:, 1] - y0) / c).astype(int), 0, ny - 1)
        s = np.zeros(nx * ny)
        n = np.zeros(nx * ny)
        np.add.at(s, iy * nx + ix, p.depth_m)
        np.add.at(n, iy * nx + ix, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            vals.append(np.where(n > 0, s / n, np.nan))
    V = _drop_unsupported(np.vstack(vals), np.array([p.noise_m for p in got]))
    D = nanmedian_last(V.T).reshape(ny, nx)
    cx = x0 + (np.arange(nx) + 0.5) * c
    cy = y0 + (np.arange(ny) + 0.5) * c
    CX, CY = np.meshgrid(cx, cy)
    in_core = contains_xy(core, CX, CY)
    in_poly = contains_xy(poly, CX, CY)
    Dm = _nanmedian3(D)
    seen = in_core & np.isfinite(D)
    if not (in_poly & np.isfinite(Dm)).any():
        return None
    max_d = supported_max(Dm[in_poly], DENSE_SUPPORT)
    if max_d is None:
        return None
    noise = float(np.median([p.noise_m for p in got]))
    rim = max(rim_floor_m, rim_k * noise)
    cover = float(seen.sum()) / max(int(in_core.sum()), 1)
    dv = D[seen]
    deep = dv >= rim
    # Cells no pair tracked count at the share of the tracked ones.
    area = float(deep.sum()) * c * c / max(cover, 1e-6)
    if extrapolate:
        # The outline is where the depth reaches 0, which noise hides: the area deeper than t
        # falls about linearly as t grows from 0 (any smooth rim), so the areas at the rim
        # threshold and at twice it extrapolate to the area at depth 0.
        a2 = float((dv >= 2 * rim).sum()) * c * c / max(cover, 1e-6)
        area = min(2 * area - a2, float(in_core.sum()) * c * c)
    vol = float(np.clip(dv, 0, None).sum()) * c * c / max(cover, 1e-6)
    mean = float(dv[deep].mean()) if deep.any() else 0.0
    return DenseMeasure(
        max_depth_m=max_d,
        mean_depth_m=mean,
        area_m2=area,
        volume_m3=vol,
        noise_m=noise,
        coverage=cover,
        n_pairs=len(got),
        origin_m=np.array([x0, y0]),
        cell_m=c,
        depth_grid_m=np.where(in_core, D, np.nan),
    )


def _drop_unsupported(V: np.ndarray, noise_m: np.ndarray) -> np.ndarray:
    """Pairs' cell depths (P, C) with a reading the other pairs that saw the cell do not
    support set to NaN: deeper than their median by more than max(5 mm, 25 %, 6 σ of the pair).

    A band of failed tracks in one pair reads decimetres deep where the other pairs read the
    floor; with two pairs the median over them is the mean of the two (a pothole 18.6 mm deep
    read 107.7 mm). Only the deeper reading is dropped: a failed track that finds a wrong
    minimum invents depth the others do not see, and a max depth read a little shallow does
    less harm than one read several times too deep. Cells one pair alone saw are kept.
    """
    if len(V) < 2:
        return V
    out = V.copy()
    for i in range(len(V)):
        others = nanmedian_last(np.delete(V, i, axis=0).T)
        tol = np.maximum(np.maximum(SUPPORT_TOL_M, 6.0 * noise_m[i]), 0.25 * np.abs(others))
        with np.errstate(invalid="ignore"):
            out[i, V[i] - others > tol] = np.nan  # NaN compares False: unshared cells stay
    return out


def _nanmedian3(D: np.ndarray) -> np.ndarray:
    """3 x 3 median ignoring NaN (NaN where the centre is NaN or fewer than 5 valid)."""
    p = np.pad(D, 1, constant_values=np.nan)
    h, w = D.shape
    stack = np.stack([p[i : i + h, j : j + w] for i in range(3) for j in range(3)])
    n = np.isfinite(stack).sum(axis=0)
    m = nanmedian_last(np.moveaxis(stack, 0, -1))
    m[(n < 5) | ~np.isfinite(D)] = np.nan
    return m


class DenseContext:
    """What the dense measurement needs from the run: the pairs, each ok pair's sparse points in
    the grid frame with their road flags, and the images (read on demand, a few kept)."""

    def __init__(
        self,
        drive: Drive,
        pairs: list[PairResult],
        pair_grid: list[tuple[int, np.ndarray, np.ndarray]],
        sparse_noise_m: float,
        workers: int = 1,
    ) -> None:
        self.camera: Camera = drive.camera
        self.pairs = pairs
        self.pair_grid = pair_grid  # (pair index, grid xy (N, 2), road (N,) bool)
        # σ of the pairs' sparse road points (median over the run): dense tracks much noisier
        # than the sparse matches of the same images have failed (wrong LK minima).
        self.sparse_noise_m = sparse_noise_m
        self.workers = max(1, int(workers))  # threads over the pairs that see one defect
        # bounded memory: a defect is seen by a few pairs, a neighbour shares their frames
        self._frames = GrayFrames(drive.frames, 9, "detection: dense measurement skips a frame")

    def gray(self, filename: str) -> np.ndarray | None:
        """The frame's grey image, or None when it is not in the drive or cannot be read."""
        return self._frames.get(filename)


def measure_defect_dense(
    poly: Polygon,
    ctx: DenseContext,
    cfg: DenseConfig,
    rim_floor_m: float,
    max_depth_m: float = 0.25,
) -> DenseMeasure | None:
    """Dense measurement of the defect inside ``poly`` from every pair whose sparse points
    reach it (``measure_dense`` per pair, ``combine_dense`` over them); None when no pair gives
    a dense reading. The caller checks ``coverage`` (a partial reading may miss the bottom)."""
    from shapely import contains_xy

    x0, y0, x1, y1 = poly.bounds
    seeing = []
    for k, xy, road in ctx.pair_grid:
        near = (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
        if near.sum() >= 3 and contains_xy(poly, xy[near, 0], xy[near, 1]).any():
            seeing.append((k, xy, road))

    def one(item: tuple[int, np.ndarray, np.ndarray]) -> PairDense | None:
        k, xy, road = item
        p = ctx.pairs[k]
        ga, gb = ctx.gray(p.frame_a), ctx.gray(p.frame_b)
        if ga is None or gb is None:
            return None
        # Level on the dense ring and the pair's sparse road points: a pair seeing part of a
        # large defect sees part of its ring only, the sparse road spans its whole overlap.
        pair_road = np.asarray(p.points_cam_a_m, float)[road]
        m = measure_dense(
            poly, ga, gb, p, xy, road, ctx.camera,
            ring_m=cfg.ring_m, edge_m=cfg.edge_m, step_px=cfg.step_px, window_px=cfg.window_px,
            road_cam_m=pair_road, max_depth_m=max_depth_m, patch_window_m=cfg.patch_window_m,
        )  # fmt: skip
        if m is not None:
            log.debug(
                "detection: dense pair %s-%s: %d tracks, depth %.1f..%.1f mm, noise %.2f mm",
                p.frame_a, p.frame_b, len(m.depth_m), 1000 * m.depth_m.min(),
                1000 * m.depth_m.max(), 1000 * m.noise_m,
            )  # fmt: skip
        return m

    # Pairs are independent and LK releases the GIL; results come back in pair order.
    got = [
        m
        for m in ordered_map(one, seeing, min(ctx.workers, len(seeing)))
        if m is not None and m.noise_m <= cfg.max_noise_k * ctx.sparse_noise_m
    ]
    res = combine_dense(
        poly, got, edge_m=cfg.edge_m, rim_k=cfg.rim_noise_k, rim_floor_m=rim_floor_m,
        extrapolate=cfg.area_extrapolate,
    )  # fmt: skip
    return res
