"""Dense surface: every ok pair's dense height (``reconstruction.dense``) fused per ground cell
into the residual raster (``MappingConfig.surface_source = "dense"``).

1. Each ok pair is matched densely (plane + parallax) on its two images: a height above the
   pair's road plane and its variance for every pixel of the overlap in its reference image
   (image a, or image b where b sees the common road nearer: ``dense_refimage``).
2. Levelling: the pair's pixels are posed in ENU with the fused pose of that frame, and a robust
   plane (offset and tilt) of their height above the local road surface (``mapping.surface``,
   fitted to the sparse points) is removed, so pairs agree where they overlap (what
   ``align_patches`` does for the sparse points).
3. Per cell of a raster tile, each pair that saw it gives one sample: the cell's centre is
   projected into the reference image at the surface's height there, its height map sampled,
   and the projection repeated at the new height (a fixed point, like a ray cast).
4. Fusion (``fuse_cells``): per cell the variance-weighted median of the pairs' samples, then
   the weighted mean of those within ``dense_outlier_sigmas`` σ of it; its count and σ.
   A pixel seen at a coarser ground footprint than the cell (far pixels of a tilted camera)
   weighs less: its variance grows by (footprint / cell)².

Tiles are fused on demand in drive order (``DenseSurface.tile``); a pair is matched when the
first tile it touches is asked for and dropped when the last one is done: memory holds the pairs
over a few tiles, never the drive.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.core.parallel import ordered_map
from roadsurf.io import runfolder as rf
from roadsurf.io.drive import Drive, GrayFrames
from roadsurf.io.formats import GridSpec
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.dense_cells import cell_samples, fuse_cells
from roadsurf.mapping.dense_refimage import reference_is_b, reversed_pair
from roadsurf.mapping.dense_seams import SeamSamples
from roadsurf.mapping.raster import GridToEnu, TileLattice
from roadsurf.mapping.surface import LocalSurface
from roadsurf.mapping.types import Trajectory
from roadsurf.reconstruction.types import PairResult

__all__ = ["DenseSurface", "DenseTile", "dense_gsd_m", "dense_px_m", "fuse_cells"]

if TYPE_CHECKING:  # torch loads only when a dense surface is built (a sparse run never needs it)
    from roadsurf.reconstruction.dense.geometry import PlaneParallax

log = logging.getLogger(__name__)

NOBS = rf.SURFACE_NOBS  # raster of the samples kept per cell (count, uint8, 0 = none)
SIGMA = rf.SURFACE_SIGMA  # raster of the σ of each cell's height (m)
# a pair levelled on the local road instead of its most populous plane needs this many of its
# points near the road (and this share of them)
_MIN_ROAD_POINTS = 200
_MIN_ROAD_SHARE = 0.03


def dense_gsd_m(cfg: MappingConfig, cam: Camera, traj: Trajectory, road_z: np.ndarray) -> float:
    """GSD of the dense rasters (m): ``dense_gsd_m`` when set, else ``dense_gsd_px`` x the
    images' ground sampling at the matching scale (median camera height over the road / fx /
    ``dense.work_scale``), but no coarser than the sparse raster's ``gsd_m`` unless one pixel
    is; rounded to 0.1 mm, never finer than ``dense_min_gsd_m``."""
    if cfg.dense_gsd_m > 0:
        return float(cfg.dense_gsd_m)
    px = dense_px_m(cfg, cam, traj, road_z)
    # dense_gsd_px pixels, but no coarser than the sparse raster unless a pixel itself is
    g = min(cfg.dense_gsd_px * px, max(px, cfg.gsd_m))
    return max(round(g * 1e4) / 1e4, cfg.dense_min_gsd_m)


def dense_px_m(cfg: MappingConfig, cam: Camera, traj: Trajectory, road_z: np.ndarray) -> float:
    """Ground size (m) of one pixel of the dense work grid at the drive's median camera height
    over the road (camera.yaml's height when the trajectory gives none)."""
    h = float(np.median(traj.world_from_cam[:, 2, 3] - road_z)) if len(traj) else cam.height_m
    if not (math.isfinite(h) and h > 0):
        h = cam.height_m
    return h / (cam.fx * cfg.dense.work_scale(cam.width, cam.height))


# --------------------------------------------------------------------------- fusion of samples


# --------------------------------------------------------------------------- one pair


@dataclass
class _PairDense:
    """A matched pair: its height map and what places it on the map."""

    index: int  # order among the ok pairs
    # the pair's plane + parallax model on the work grid; of its DenseHeight only this is kept
    # (its other per-pixel arrays, ~1.7 MB a pair at 320 x 240, are dead weight while the
    # pair waits for its last tile)
    model: PlaneParallax
    n_valid: int  # pixels with a height (count)
    R_wc: np.ndarray  # (3, 3) ENU from camera a (fused pose)
    C: np.ndarray  # (3,) camera a's centre (ENU)
    level: np.ndarray  # (3,) plane removed from its residuals: a + b (e - e0) + c (n - n0)
    level_at: np.ndarray  # (2,) e0, n0
    height_filled: np.ndarray  # (h, w) float32 heights, 0 where invalid (for sampling)
    valid_f: np.ndarray  # (h, w) float32 1 where valid
    var: np.ndarray  # (h, w) float32 variance, 0 where invalid


@dataclass
class DenseTile:
    residual_m: np.ndarray  # (H, W) float32 height above the local road (m), NaN: unobserved
    n_obs: np.ndarray  # (H, W) int32 samples kept per cell
    sigma_m: np.ndarray  # (H, W) float32 σ of the estimate (m)


class DenseSurface:
    """Dense residual tiles on demand (module docstring). Thread-safe: tiles may be asked for
    from several threads; pairs are matched in drive order, ``workers`` at a time."""

    def __init__(
        self,
        cfg: MappingConfig,
        drive: Drive,
        pairs: list[PairResult],
        traj: Trajectory,
        surf: LocalSurface,
        g2e: GridToEnu,
        lat: TileLattice,
        tiles: list[tuple[int, int]],
        fp_grid: list[np.ndarray],
        workers: int,
    ) -> None:
        self.cfg, self.cam, self.traj, self.surf, self.g2e, self.lat = (
            cfg, drive.camera, traj, surf, g2e, lat,
        )  # fmt: skip
        self.workers = max(1, int(workers))
        pose_of = {fn: i for i, fn in enumerate(traj.filenames)}
        ok = [
            p
            for p in pairs
            if p.ok and p.frame_a in pose_of and p.frame_b in pose_of and np.isfinite(p.plane).all()
        ]
        self.pairs = ok
        self.pose_a = [pose_of[p.frame_a] for p in ok]
        self.pose_b = [pose_of[p.frame_b] for p in ok]
        # each pair measured on the image that sees its common road nearer (dense_refimage)
        W = traj.world_from_cam
        self.ref_b = [
            cfg.dense_match_image == "nearer" and reference_is_b(drive.camera, W[ia], W[ib])
            for ia, ib in zip(self.pose_a, self.pose_b, strict=True)
        ]
        self.pose_ref = [
            ib if rb else ia
            for ia, ib, rb in zip(self.pose_a, self.pose_b, self.ref_b, strict=True)
        ]
        self.images = GrayFrames(drive.frames, 4, "dense surface")
        # tiles each pair may touch: its reference frame's footprint, widened by the relief's
        # reach
        wanted = set(tiles)
        fg = lat.full_grid
        tp = lat.tile_px
        pad = 0.1 / lat.gsd_m
        self.pair_tiles: list[set[tuple[int, int]]] = []
        self.pair_box: list[tuple[int, int, int, int] | None] = []
        for i in self.pose_ref:
            fp = fp_grid[i]
            if len(fp) < 3:
                self.pair_tiles.append(set())
                self.pair_box.append(None)
                continue
            rc = fg.rowcol_from_xy(fp)
            r0, c0 = (np.floor(rc.min(0) - pad)).astype(int)
            r1, c1 = (np.ceil(rc.max(0) + pad)).astype(int)
            self.pair_box.append((r0, r1, c0, c1))
            ts = {
                (tr, tc)
                for tr in range(max(r0 // tp, 0), min(r1 // tp, lat.n_rows - 1) + 1)
                for tc in range(max(c0 // tp, 0), min(c1 // tp, lat.n_cols - 1) + 1)
            }
            self.pair_tiles.append(ts & wanted)
        self.tile_pairs: dict[tuple[int, int], list[int]] = {t: [] for t in tiles}
        for k, ts in enumerate(self.pair_tiles):
            for t in ts:
                self.tile_pairs[t].append(k)
        self._lock = threading.Lock()
        self._next = 0  # next pair to match
        self._done: dict[int, _PairDense | None] = {}
        self._tiles_left = [set(ts) for ts in self.pair_tiles]
        self.stats = {"pairs": 0, "pairs_failed": 0, "match_s": 0.0, "valid_px": 0}
        self.seams: SeamSamples | None = None  # set: the pairs' samples where they overlap

    # ------------------------------------------------------------------ pairs
    def _match(self, k: int) -> _PairDense | None:
        p = self.pairs[k]
        a, b = self.images.get(p.frame_a), self.images.get(p.frame_b)
        if a is None or b is None:
            return None
        from roadsurf.reconstruction.dense.parallax import dense_height

        try:
            # a rolling shutter's rows are placed in time, when the pair's R, t come from the
            # rolling-shutter model (a global-shutter fit has absorbed part of the skew)
            ts = self.traj.timestamp_s
            dt: float | None = float(ts[self.pose_b[k]] - ts[self.pose_a[k]])
            if "rs_iterations" not in p.config_name:
                dt = None
            if self.ref_b[k]:  # measured on image b: its time first (a rolling shutter)
                R_ab, t_ab, plane_b = reversed_pair(p)
                dh = dense_height(
                    b, a, self.cam, R_ab, t_ab, plane_b, None, self.cfg.dense,
                    frame_dt_s=None if dt is None else -dt,
                )  # fmt: skip
            else:
                dh = dense_height(
                    a, b, self.cam, p.R_b_from_a, p.t_b_from_a_m, p.plane, p.H, self.cfg.dense,
                    frame_dt_s=dt,
                )  # fmt: skip
        except Exception as e:  # a pair that cannot be matched leaves its cells to the others
            log.warning("dense surface: pair %s -> %s not matched (%s)", p.frame_a, p.frame_b, e)
            return None
        W = self.traj.world_from_cam[self.pose_ref[k]]
        R, C = W[:3, :3], W[:3, 3]
        # about 20,000 of the valid pixels level the pair
        vv, uu = np.nonzero(dh.valid)
        sel = slice(None, None, max(1, len(vv) // 20000))
        vv, uu = vv[sel], uu[sel]
        X = dh.model.points_cam_a(
            dh.height_m[vv, uu].astype(float), uu.astype(float), vv.astype(float)
        )
        Xw = X @ R.T + C
        road = self.surf.height(Xw[:, :2])
        if self.cfg.dense_reference == "pair_plane":
            r = Xw[:, 2]
        else:
            r, road = Xw[:, 2] - road, np.zeros_like(road)
        coef, at = _robust_plane(
            Xw[:, :2], r, self.cfg.local_fit_inlier_m, self.cfg.dense_reference != "pair_plane",
            road,
        )  # fmt: skip

        v = dh.valid
        return _PairDense(
            k,
            dh.model,
            int(v.sum()),
            R,
            C,
            coef,
            at,
            np.where(v, dh.height_m, 0).astype(np.float32),
            v.astype(np.float32),
            np.where(v, dh.var_m2, 0).astype(np.float32),
        )

    def _advance(self, upto: int) -> None:
        """Match pairs up to ``upto`` (inclusive), ``workers`` at a time (caller holds the lock)."""
        todo = list(range(self._next, upto + 1))
        if not todo:
            return
        t0 = time.perf_counter()
        for k, pdn in zip(todo, ordered_map(self._match, todo, self.workers), strict=True):
            self._done[k] = pdn
            self.stats["pairs"] += 1
            if pdn is None:
                self.stats["pairs_failed"] += 1
            else:
                self.stats["valid_px"] += pdn.n_valid
        self._next = upto + 1
        self.stats["match_s"] += time.perf_counter() - t0

    # ------------------------------------------------------------------ tiles
    def tile(self, t: tuple[int, int]) -> DenseTile:
        ks = self.tile_pairs.get(t, [])
        with self._lock:
            if ks:
                self._advance(max(ks))
            got = [self._done[k] for k in ks]
        grid = self.lat.tile_grid(*t)
        n = grid.width * grid.height
        cells, vals, vars_ = [], [], []
        frames: list[int] = []
        for pdn in got:
            if pdn is None:
                continue
            out = self._sample(pdn, grid, t)
            if out is not None:
                cells.append(out[0])
                vals.append(out[1])
                vars_.append(out[2])
                frames.append(int(self.pairs[pdn.index].index_a))
        if self.seams is not None:
            tp = self.lat.tile_px
            self.seams.add(
                t[0] * tp, t[1] * tp, grid.width, list(zip(frames, cells, vals, strict=True))
            )
        with self._lock:  # drop pairs whose every tile is done
            for k in ks:
                self._tiles_left[k].discard(t)
                if not self._tiles_left[k]:
                    self._done.pop(k, None)
        if cells:
            est, cnt, sig = fuse_cells(
                np.concatenate(cells),
                np.concatenate(vals),
                np.concatenate(vars_),
                n,
                self.cfg.dense_outlier_sigmas,
            )
        else:
            est = np.full(n, np.nan, np.float32)
            cnt, sig = np.zeros(n, np.int32), np.full(n, np.nan, np.float32)
        shape = (grid.height, grid.width)
        return DenseTile(est.reshape(shape), cnt.reshape(shape), sig.reshape(shape))

    def _sample(
        self, pdn: _PairDense, grid: GridSpec, t: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """One sample per cell of the tile that the pair saw: (cell index, residual, variance)."""
        box = self.pair_box[pdn.index]
        if box is None:
            return None
        tp = self.lat.tile_px
        R0, C0 = t[0] * tp, t[1] * tp
        r0, r1 = max(box[0] - R0, 0), min(box[1] - R0, grid.height - 1)
        c0, c1 = max(box[2] - C0, 0), min(box[3] - C0, grid.width - 1)
        if r1 < r0 or c1 < c0:
            return None
        e, n = self.g2e.pixel_enu(grid, slice(r0, r1 + 1), slice(c0, c1 + 1))
        lev = (
            pdn.level[0]
            + pdn.level[1] * (e - pdn.level_at[0])
            + pdn.level[2] * (n - pdn.level_at[1])
        )
        if self.cfg.dense_reference == "pair_plane":
            zs, lev = lev, np.zeros_like(lev)
        else:
            zs = surface_height_grid(self.surf, e, n, grid.gsd_m)
        z = np.where(np.isfinite(zs), zs, pdn.C[2] - self.cam.height_m)
        got = cell_samples(
            pdn.model, pdn.R_wc, pdn.C, pdn.height_filled, pdn.valid_f, pdn.var, e, n, z,
            grid.gsd_m, self.cfg.dense_visible_k,
        )  # fmt: skip
        if got is None:
            return None
        ok, r, var = got
        ok &= np.isfinite(zs)
        if not ok.any():
            return None
        rows, cols = np.nonzero(ok)
        var = var[ok]
        cell = (rows + r0) * grid.width + (cols + c0)
        return cell, (r - lev)[ok], var


def surface_height_grid(surf: LocalSurface, e: np.ndarray, n: np.ndarray, gsd: float) -> np.ndarray:
    """The local road height at ENU e, n (H, W): evaluated every ~4 cm and upsampled (the fit is
    smooth on its node scale), NaN where it has no node."""
    st = max(1, int(round(0.04 / gsd)))
    es, ns = e[::st, ::st], n[::st, ::st]
    zs = surf.height(np.column_stack([es.ravel(), ns.ravel()])).reshape(es.shape)
    if st == 1:
        return zs
    # bilinear on the node samples: exact at every st-th cell, NaN spreads to its neighbours
    H, W = e.shape
    ri = np.arange(H) / st
    ci = np.arange(W) / st
    return cv2.remap(
        zs.astype(np.float32),
        np.tile(ci.astype(np.float32), (H, 1)),
        np.tile(ri.astype(np.float32)[:, None], (1, W)),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(float)


def _robust_plane(
    xy: np.ndarray, r: np.ndarray, inlier_m: float, near_zero: bool, road: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(a, b, c) and the centre (e0, n0) of the road plane r ≈ a + b (e - e0) + c (n - n0) in
    the finite residuals, then refitted to the points within max(3 MAD, 3 mm) of it. The start
    is the plane 0 (``near_zero``: residuals to a surface already fitted across pairs; points
    within ``inlier_m`` of it) or, when that holds too few points or without one, the plane with
    most points within 3 mm among 3-point samples (RANSAC): a least-squares start is pulled
    off the road by a pothole that fills half the view, and trimming never recovers. ``road``
    (N,): the local road surface at xy in r's terms (NaN: none); a start plane that lies more
    than ``inlier_m`` below it while the points within ``inlier_m`` of it lie more than that over
    the start (a pothole's floor filling most of the view holds most points within 3 mm of one
    plane) is replaced by the densest plane among those points, when there are enough and it is
    a density peak, and the refit keeps to them (a pair's own offset moves all its points alike
    and passes). Zeros when too few points."""
    m = np.isfinite(r)
    if m.sum() < 50:
        return np.zeros(3), np.zeros(2)
    at = np.median(xy[m], axis=0)
    A = np.column_stack([np.ones(m.sum()), xy[m] - at])
    y = r[m]
    band = 0.003
    keep = np.abs(y) < inlier_m if near_zero else np.zeros(len(y), bool)
    gate = np.ones(len(y), bool)
    if keep.sum() < 0.2 * len(y):
        keep = _ransac_band(A, y, np.arange(len(y)), band)
    if road is not None:
        ry = np.asarray(road, float)[m]
        fin = np.isfinite(ry)
        near = fin & (np.abs(y - ry) < inlier_m)
        if keep.sum() >= 3 and near.sum() >= max(_MIN_ROAD_POINTS, _MIN_ROAD_SHARE * len(y)):
            c0 = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
            below = np.median((A @ c0 - ry)[fin])  # the start plane under the road (m)
            over = np.median((y - A @ c0)[near])  # the road's points over the start plane (m)
            if below < -inlier_m and over > inlier_m:
                # the densest plane among the points near the road (the upper walls are near
                # it too), and the refit stays among them: else it takes in the walls and
                # walks back down into the floor
                cand = _ransac_band(A, y, np.flatnonzero(near), band)
                c1 = np.linalg.lstsq(A[cand], y[cand], rcond=None)[0]
                # a density peak, not the upper tail of a noisy pair offset from the surface
                # (all road, 15 mm under it, σ 5 mm): more points in its band than in the band
                # 2 x band under it
                if cand.sum() > (np.abs(y - A @ c1 + 2 * band) < band).sum():
                    keep, gate = cand, near
    coef = np.zeros(3)
    for _ in range(8):
        if keep.sum() < 20:
            break
        coef = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        res = y - A @ coef
        mad = MAD_TO_SIGMA * float(np.median(np.abs(res[keep])))
        new = (np.abs(res) < max(3 * mad, band)) & gate
        if np.array_equal(new, keep):
            break
        keep = new
    return coef, at


def _ransac_band(A: np.ndarray, y: np.ndarray, among: np.ndarray, band: float) -> np.ndarray:
    """(N,) bool: the points within ``band`` (m) of the plane y ≈ A coef (A (N, 3): 1, dx, dy)
    that holds most of the points ``among`` (indices) within it, out of 200 planes through 3
    of them (a fixed seed: the same pair levels the same way)."""
    rng = np.random.default_rng(0)
    sub = rng.choice(among, min(len(among), 3000), replace=False)
    # 200 3-point planes at once; degenerate triples (collinear) score nothing
    idx = sub[rng.integers(0, len(sub), (200, 3))]
    M, b = A[idx], y[idx]
    ok = np.abs(np.linalg.det(M)) > 1e-12
    coefs = np.zeros((200, 3))
    coefs[ok] = np.linalg.solve(M[ok], b[ok][..., None])[..., 0]
    As, ys = A[sub], y[sub]
    pred = coefs[:, :1] + coefs[:, 1:2] * As[:, 1] + coefs[:, 2:3] * As[:, 2]
    n_in = np.where(ok, (np.abs(ys - pred) < band).sum(axis=1), -1)
    best = coefs[int(np.argmax(n_in))]
    return np.abs(y - (best[0] + best[1] * A[:, 1] + best[2] * A[:, 2])) < band
