"""Ray-casting renderer: each (supersampled) pixel's ray is intersected with the height field.

The world is evaluated lazily in square tiles of ~``TILE_M`` (at most ``TILE`` px) at the render GSD (finer than the
pixel footprint) and kept in a small LRU cache; a frame assembles the few tiles under its
footprint into a mosaic and samples it with ``cv2.remap`` (bilinear). Memory therefore scales
with the footprint, not with the route.

Ray/height-field intersection: start on the plane under the camera, then iterate
t <- (h(x(t), y(t)) - C_z) / d_z a few times (fixed point; converges while the surface slope
times the ray's tangent stays below 1, which holds for the bowls and grooves a nadir camera
sees). A tilted mount's far rays are flat (tangent 2-3): there the rays that have not settled
after those steps go on in a safeguarded search that keeps a bracket [above, below the
surface] per ray and bisects when a step would leave it.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
from shapely.geometry import MultiPoint, Polygon, box
from shapely.prepared import prep

from roadsurf.core.camera import RENDER_UNDISTORT_CRITERIA
from roadsurf.simulation.route import Pose
from roadsurf.simulation.world import World

# frame labels: the footprint area deeper than this counts as defect (m; truth.DEFECT_AREA_M2)
LABEL_DEPTH_M = 0.010

TILE = 384  # largest tile size (px at the render GSD)
TILE_M = 0.47  # target tile size on the ground (m): coarse GSDs get smaller tiles
ROW_KNOT = 8  # rolling shutter: an exact pose every this many supersampled rows (count)
SETTLED = 0.1  # a tilted view's ray whose last fixed-point step moved more than this share of
# its ground size has not settled: a bracketed search finishes it


@dataclass
class FrameRender:
    radiance: np.ndarray  # (H, W, 3) float32 linear radiance (≈ albedo on flat lit road)
    defect_area_m2: float  # footprint area with a defect deeper than 10 mm (m^2)
    max_depth_m: float  # deepest defect point in the footprint (m)
    footprint: np.ndarray  # (16, 2) local x, y of points around the image border on the road


class Renderer:
    """Renders frames of one world. Not thread-safe (tile cache)."""

    def __init__(self, world: World, cache_tiles: int = 40) -> None:
        self.world = world
        c = world.cfg
        self.g = world.render_gsd_m
        self.ss = max(1, int(c.supersample))
        self.tile = int(np.clip(round(TILE_M / self.g / 16) * 16, 64, TILE))
        self.cache: OrderedDict[tuple[int, int], tuple[np.ndarray, ...]] = OrderedDict()
        self.cache_tiles = cache_tiles
        self.tile_seconds = 0.0  # time spent evaluating world tiles (for benchmarks)
        self.tiles_made = 0
        self.mounted = c.mounted
        # Deepest a ray can reach below the smooth road (defects, unevenness): pads a tilted
        # view's mosaic by this times the flattest ray's tangent (m).
        self.relief_m = max(c.pothole_depth_m[1], 0.02) + 4.0 * c.unevenness_m + 0.005
        W, H = c.width * self.ss, c.height * self.ss
        u = (np.arange(W, dtype=np.float64) + 0.5) / self.ss - 0.5
        v = (np.arange(H, dtype=np.float64) + 0.5) / self.ss - 0.5
        U, V = np.meshgrid(u, v)
        self.camera = c.camera()
        n = self.camera.normalised_from_raw_px(
            np.column_stack([U.ravel(), V.ravel()]), criteria=RENDER_UNDISTORT_CRITERIA
        )
        rays = np.column_stack([n, np.ones(len(n))]).reshape(H, W, 3)
        self.rays_cam = rays.astype(np.float32)  # z = 1
        az, el = math.radians(c.sun_azimuth_deg), math.radians(c.sun_elevation_deg)
        self.light = np.array(
            [math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)], np.float32
        )

    # ---- tiles
    def _tile(self, a: int, b: int) -> tuple[np.ndarray, ...]:
        key = (a, b)
        if key in self.cache:
            self.cache.move_to_end(key)
            return self.cache[key]
        t_start = time.perf_counter()
        g, n = self.g, self.tile
        x0 = a * n * g - g
        y_top = -b * n * g + g
        f = self.world.evaluate(x0, y_top, g, n + 2, n + 2, appearance=True)
        h = f["height"]
        gx = (h[1:-1, 2:] - h[1:-1, :-2]) / (2 * g)  # dz/dx (east)
        gy = (h[:-2, 1:-1] - h[2:, 1:-1]) / (2 * g)  # dz/dy (north; rows go south)
        inv = 1.0 / np.sqrt(gx * gx + gy * gy + 1.0)
        L = self.light
        ndotl = np.clip((-gx * L[0] - gy * L[1] + L[2]) * inv, 0.0, None) / max(float(L[2]), 0.05)
        amb = np.float32(self.world.cfg.ambient)
        # Ambient light is reduced slightly in steep spots (cheap ambient occlusion).
        light = amb * inv + (1 - amb) * (1 - f["shadow"][1:-1, 1:-1]) * ndotl
        rad = f["rgb"][1:-1, 1:-1] * light[..., None]
        tile = (
            np.ascontiguousarray(h[1:-1, 1:-1], dtype=np.float32),
            np.ascontiguousarray(rad, dtype=np.float32),
            np.ascontiguousarray(f["depth"][1:-1, 1:-1], dtype=np.float32),
        )
        self.cache[key] = tile
        self.tiles_made += 1
        self.tile_seconds += time.perf_counter() - t_start
        while len(self.cache) > self.cache_tiles:
            self.cache.popitem(last=False)
        return tile

    def _mosaic(
        self, xmin: float, ymin: float, xmax: float, ymax: float, area: Polygon | None = None
    ):
        """Tiles over the box, assembled. With ``area`` (a tilted view's padded footprint)
        tiles outside it are not evaluated: no ray reaches them (flat filler instead)."""
        g, n = self.g, self.tile
        a0, a1 = math.floor(xmin / (n * g)), math.floor(xmax / (n * g))
        b0, b1 = math.floor(-ymax / (n * g)), math.floor(-ymin / (n * g))
        rows, cols = (b1 - b0 + 1) * n, (a1 - a0 + 1) * n
        H = np.empty((rows, cols), np.float32)
        R = np.empty((rows, cols, 3), np.float32)
        D = np.empty((rows, cols), np.float32)
        tiles = [(a, b) for b in range(b0, b1 + 1) for a in range(a0, a1 + 1)]
        if area is not None:
            inside = prep(area)
            tiles = [
                (a, b)
                for a, b in tiles
                if inside.intersects(box(a * n * g, -(b + 1) * n * g, (a + 1) * n * g, -b * n * g))
            ]
        # Keep two frames' tiles: consecutive frames share most of them (no LRU thrashing).
        self.cache_tiles = max(self.cache_tiles, 2 * len(tiles))
        wanted = set(tiles)
        for b in range(b0, b1 + 1):
            for a in range(a0, a1 + 1):
                rs, cs = (b - b0) * n, (a - a0) * n
                if (a, b) in wanted:
                    h, r, d = self._tile(a, b)
                else:  # flat filler at the road's height there
                    zb = self.world.base(np.array((a + 0.5) * n * g), np.array(-(b + 0.5) * n * g))
                    h, r, d = np.float32(zb), 0.0, 0.0
                H[rs : rs + n, cs : cs + n] = h
                R[rs : rs + n, cs : cs + n] = r
                D[rs : rs + n, cs : cs + n] = d
        return H, R, D, a0 * n * g, -b0 * n * g

    # ---- frames
    def footprint(self, pose: Pose, z_ground: float) -> np.ndarray:
        """(16, 2) points around the image border on the road (local metres); the first,
        fifth, ninth and thirteenth are the image corners. The road is the plane z = z_ground
        for the nadir camera; a tilted view reaches metres ahead, so there it is the smooth
        road surface (``World.base``: grade, cross slope, undulation).

        Not ``Camera.footprint_corners_enu``/``footprint_grid_enu``: 16 pixel-edge points, lens
        distortion undone with the renderer's stopping rule, so the rendered mosaic covers the
        distorted image."""
        d = self._border_rays(pose)
        t = (z_ground - pose.C[2]) / d[:, 2]
        if self.mounted:
            for _ in range(3):  # fixed point on the smooth surface (slopes of a few %)
                xy = pose.C[:2] + t[:, None] * d[:, :2]
                t = (self.world.base(xy[:, 0], xy[:, 1]) - pose.C[2]) / d[:, 2]
        return pose.C[:2] + t[:, None] * d[:, :2]

    def _border_px(self) -> tuple[np.ndarray, np.ndarray]:
        """(16,) raw rows v and (16, 2) normalised camera coordinates of the image border's
        pixel edges (four per side, clockwise from the top-left corner)."""
        c = self.world.cfg
        f = np.linspace(0.0, 1.0, 4, endpoint=False)
        w, h = c.width - 0.5, c.height - 0.5
        u = np.concatenate([-0.5 + f * c.width, np.full(4, w), w - f * c.width, np.full(4, -0.5)])
        v = np.concatenate([np.full(4, -0.5), -0.5 + f * c.height, np.full(4, h), h - f * c.height])
        n = self.camera.normalised_from_raw_px(
            np.column_stack([u, v]), criteria=RENDER_UNDISTORT_CRITERIA
        )
        return v, n

    def _border_rays(self, pose: Pose) -> np.ndarray:
        """(16, 3) world directions (camera z = 1) through the image border's pixel edges."""
        _, n = self._border_px()
        return np.column_stack([n, np.ones(len(n))]) @ pose.R.T

    def row_poses(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """Rolling shutter: (Hs, 3) centres and (Hs, 3, 3) world_from_cam rotations of the
        supersampled rows, raw row v (pixel centres, 0 = top) from the pose at
        ``pose.t + readout_s * v / height`` (the frame's timestamp is its first row's)."""
        c = self.world.cfg
        v = (np.arange(c.height * self.ss, dtype=np.float64) + 0.5) / self.ss - 0.5
        # Exact poses every ROW_KNOT rows (and the last), linear in between: the trajectory is
        # itself piecewise linear in 5 ms steps, a knot interval is < 0.1 ms of a 20 ms readout.
        knots = np.unique(np.append(np.arange(0, len(v), ROW_KNOT), len(v) - 1))
        poses = [self.world.pose(pose.t + c.readout_s * v[k] / c.height) for k in knots]
        C = np.array([p.C for p in poses])
        R = np.array([p.R for p in poses]).reshape(len(knots), 9)
        rows = np.arange(len(v))
        Cr = np.column_stack([np.interp(rows, knots, C[:, j]) for j in range(3)])
        Rr = np.column_stack([np.interp(rows, knots, R[:, j]) for j in range(9)])
        return Cr, Rr.reshape(-1, 3, 3)

    def _border_rolling(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """Rolling shutter: (16, 3) centres and (16, 3) world directions of the border rays
        of ``_border_rays``, each from its own row's pose."""
        c = self.world.cfg
        v, n = self._border_px()
        poses = [self.world.pose(pose.t + c.readout_s * vi / c.height) for vi in v]
        d = np.array([p.R @ np.append(ni, 1.0) for p, ni in zip(poses, n, strict=True)])
        return np.array([p.C for p in poses]), d

    def _footprint_rolling(self, pose: Pose, z_ground: float) -> np.ndarray:
        """``footprint`` of a rolling-shutter frame: each border point from its row's pose."""
        Cb, d = self._border_rolling(pose)
        t = (z_ground - Cb[:, 2]) / d[:, 2]
        if self.mounted:
            for _ in range(3):
                xy = Cb[:, :2] + t[:, None] * d[:, :2]
                t = (self.world.base(xy[:, 0], xy[:, 1]) - Cb[:, 2]) / d[:, 2]
        return Cb[:, :2] + t[:, None] * d[:, :2]

    def render(self, pose: Pose) -> FrameRender:
        """The frame whose timestamp is ``pose.t``; with a rolling shutter (``readout_s``)
        each supersampled row from its own pose (``row_poses``)."""
        c = self.world.cfg
        C = pose.C
        z_ground = float(self.world.base(np.array(C[0]), np.array(C[1])))
        rows = self.row_poses(pose) if c.readout_s > 0 else None
        if rows is None:
            fp = self.footprint(pose, z_ground)
        else:
            fp = self._footprint_rolling(pose, z_ground)
        pad = 0.12 + 0.05 * (C[2] - z_ground)
        if not self.mounted:
            area = None
            box_m = (fp[:, 0].min() - pad, fp[:, 1].min() - pad)
            box_m += (fp[:, 0].max() + pad, fp[:, 1].max() + pad)
        else:
            # A border ray meets the surface up to relief_m below the smooth road: that far
            # on along its direction (its tangent times relief_m, metres for flat far rays).
            dw = self._border_rays(pose) if rows is None else self._border_rolling(pose)[1]
            beyond = fp + self.relief_m * dw[:, :2] / -dw[:, 2:3]
            area = MultiPoint(np.vstack([fp, beyond])).convex_hull.buffer(pad)
            box_m = area.bounds
        H, Rm, D, mx0, my0 = self._mosaic(*box_m, area)
        g = self.g
        zoff = None  # per-row camera height relative to C (rolling shutter), else none
        if rows is None:
            d = (self.rays_cam @ pose.R.T.astype(np.float32)).astype(np.float32)  # world dirs
            # Mosaic pixel coordinates are affine in the ray parameter t (z-depth: ray z = 1).
            col0 = np.float32((C[0] - mx0) / g - 0.5)
            row0 = np.float32((my0 - C[1]) / g - 0.5)
        else:
            Cr, Rr = rows
            d = np.matmul(self.rays_cam, Rr.transpose(0, 2, 1).astype(np.float32))
            col0 = ((Cr[:, :1] - mx0) / g - 0.5).astype(np.float32)
            row0 = ((my0 - Cr[:, 1:2]) / g - 0.5).astype(np.float32)
            zoff = (Cr[:, 2:3] - C[2]).astype(np.float32)
        inv_dz = np.float32(1.0) / d[..., 2]
        dcol = d[..., 0] / np.float32(g)
        drow = -d[..., 1] / np.float32(g)
        Hrel = H - np.float32(C[2])  # heights relative to the camera (small numbers, float32)

        if not self.mounted:
            # Start on the plane under the camera; fixed-point iterations on the height field.
            t = np.float32(z_ground - C[2]) * inv_dz
            if zoff is not None:
                t = (np.float32(z_ground - C[2]) - zoff) * inv_dz
            for _ in range(max(1, c.raycast_iters)):
                t = _height_at(Hrel, col0, row0, dcol, drow, t, zoff) * inv_dz
        else:
            # Start on the plane through the footprint on the smooth road (metres ahead, the
            # road's grade and cross slope matter), then iterate.
            xy = fp - C[:2]
            zb = self.world.base(fp[:, 0], fp[:, 1]) - C[2]
            a, bx, by = np.linalg.lstsq(np.column_stack([np.ones(len(xy)), xy]), zb, rcond=None)[0]
            den = d[..., 2] - np.float32(bx) * d[..., 0] - np.float32(by) * d[..., 1]
            if rows is None:
                t = np.float32(a) / den
            else:  # the plane z - C_z = a + bx (x - C_x) + by (y - C_y) from each row's centre
                dC = rows[0] - C
                num = a + bx * dC[:, :1] + by * dC[:, 1:2] - dC[:, 2:3]
                t = num.astype(np.float32) / den
            t = _intersect_tilted(
                Hrel, col0, row0, dcol, drow, inv_dz, t, c.raycast_iters, g, c.fx * self.ss, zoff
            )
        col = col0 + t * dcol
        row = row0 + t * drow
        rad = cv2.remap(Rm, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        dep = cv2.remap(D, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if self.ss > 1:
            rad = cv2.resize(rad, (c.width, c.height), interpolation=cv2.INTER_AREA)
        # Ground area seen by each ray: t² / (fx fy |d_z|) of a pixel, 1/ss² of it per ray
        # (z-depth t, world ray d with camera z = 1); |d_z| = 1 for the level nadir camera.
        if not self.mounted:
            cell = (t / c.fx) ** 2 / (self.ss * self.ss)
        else:
            cell = t * t * np.abs(inv_dz) / np.float32(c.fx * c.fx * self.ss * self.ss)
        deep = dep > LABEL_DEPTH_M
        area_m2 = float(np.sum(cell[deep]))
        return FrameRender(rad, area_m2, float(dep.max()) if dep.size else 0.0, fp)


def _height_at(Hrel, col0, row0, dcol, drow, t: np.ndarray, zoff=None) -> np.ndarray:
    """Mosaic height (relative to the camera) where the rays reach parameter t (bilinear);
    ``zoff``: each row's camera height above the mosaic's reference (rolling shutter)."""
    h = cv2.remap(
        Hrel, col0 + t * dcol, row0 + t * drow, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return h if zoff is None else h - zoff


def _intersect_tilted(
    Hrel, col0, row0, dcol, drow, inv_dz, t: np.ndarray, iters: int, g: float, fx_ss: float,
    zoff=None,
):  # fmt: skip
    """Ray parameter t where the rays of a tilted view meet the height field. Fixed-point
    steps for all rays; those still moving after ``iters`` steps (flat rays over steep walls,
    where the fixed point oscillates) go on in a bracketed search (``_safeguarded``).
    col0, row0, zoff: scalars, or (rows, 1) per row with a rolling shutter (``_height_at``)."""
    for _ in range(max(1, iters)):
        t_prev = t
        t = _height_at(Hrel, col0, row0, dcol, drow, t, zoff) * inv_dz
    # Last step on the ground against the ray's own ground size (sqrt of its ``cell``): far
    # rays see centimetres, so they settle at a coarser tolerance than near ones.
    moved = np.abs(t - t_prev) * np.hypot(dcol, drow) * np.float32(g)
    size = t * np.sqrt(np.abs(inv_dz)) / np.float32(fx_ss)
    idx = np.flatnonzero(moved > np.float32(SETTLED) * size)
    if idx.size == 0:
        return t
    # The unsettled rays as (k, 1024) maps: cv2.remap's maps stay below 32767 px a side.
    width = 1024
    pad = (-idx.size) % width

    def take(a):
        return np.pad(a.ravel()[idx], (0, pad), mode="edge").reshape(-1, width)

    dc, dr, inv = take(dcol), take(drow), take(inv_dz)
    h_max = float(Hrel.max())
    if zoff is None:
        c0, r0, zo = col0, row0, None
    else:  # per-row values, per unsettled ray
        c0, r0, zo = (take(np.broadcast_to(a, t.shape)) for a in (col0, row0, zoff))
        h_max -= float(zoff.min())
    ts = _safeguarded(
        lambda tt: _height_at(Hrel, c0, r0, dc, dr, tt, zo), take(t), inv, h_max, 2 * iters
    )
    out = t.ravel().copy()
    out[idx] = ts.ravel()[: idx.size]
    return out.reshape(t.shape)


def _safeguarded(height_at, t: np.ndarray, inv_dz: np.ndarray, h_max: float, iters: int):
    """Fixed-point steps t <- h(x(t)) / d_z inside a per-ray bracket [lo above the surface,
    hi below it]; a bisection where a step would leave it. ``h_max``: the highest surface
    point relative to the camera (every ray is above the surface before it gets that low)."""
    lo = np.maximum(np.float32(h_max) * inv_dz, np.float32(0.0))
    hi = np.full_like(t, np.inf)
    for _ in range(max(1, iters)):
        t_fp = height_at(t) * inv_dz  # >= t where the ray is still above the surface
        above = t <= t_fp
        lo = np.where(above, np.maximum(lo, t), lo)
        hi = np.where(above, hi, np.minimum(hi, t))
        mid = np.where(np.isfinite(hi), np.float32(0.5) * (lo + hi), lo)
        t = np.where((t_fp < lo) | (t_fp > hi), mid, t_fp)
    return t
