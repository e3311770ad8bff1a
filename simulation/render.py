"""Ray-casting renderer: each (supersampled) pixel's ray is intersected with the height field.

The world is evaluated lazily in square tiles of ~``TILE_M`` (at most ``TILE`` px) at the render GSD (finer than the
pixel footprint) and kept in a small LRU cache; a frame assembles the few tiles under its
footprint into a mosaic and samples it with ``cv2.remap`` (bilinear). Memory therefore scales
with the footprint, not with the route.

Ray/height-field intersection: start on the plane under the camera, then iterate
t <- (h(x(t), y(t)) - C_z) / d_z a few times (fixed point; converges while the surface slope
times the ray's tangent stays below 1, which holds for the bowls and grooves rendered here).
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from roadsurf.core.camera import RENDER_UNDISTORT_CRITERIA
from roadsurf.simulation.route import Pose
from roadsurf.simulation.world import World

TILE = 384  # largest tile size (px at the render GSD)
TILE_M = 0.47  # target tile size on the ground (m): coarse GSDs get smaller tiles


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

    def _mosaic(self, xmin: float, ymin: float, xmax: float, ymax: float):
        g, n = self.g, self.tile
        a0, a1 = math.floor(xmin / (n * g)), math.floor(xmax / (n * g))
        b0, b1 = math.floor(-ymax / (n * g)), math.floor(-ymin / (n * g))
        rows, cols = (b1 - b0 + 1) * n, (a1 - a0 + 1) * n
        H = np.empty((rows, cols), np.float32)
        R = np.empty((rows, cols, 3), np.float32)
        D = np.empty((rows, cols), np.float32)
        for b in range(b0, b1 + 1):
            for a in range(a0, a1 + 1):
                h, r, d = self._tile(a, b)
                rs, cs = (b - b0) * n, (a - a0) * n
                H[rs : rs + n, cs : cs + n] = h
                R[rs : rs + n, cs : cs + n] = r
                D[rs : rs + n, cs : cs + n] = d
        return H, R, D, a0 * n * g, -b0 * n * g

    # ---- frames
    def footprint(self, pose: Pose, z_ground: float) -> np.ndarray:
        """(16, 2) points around the image border on the plane z = z_ground (local metres);
        the first, fifth, ninth and thirteenth are the image corners.

        Not ``Camera.footprint_corners_enu``/``footprint_grid_enu``: 16 pixel-edge points, lens
        distortion undone with the renderer's stopping rule, so the rendered mosaic covers the
        distorted image."""
        c = self.world.cfg
        f = np.linspace(0.0, 1.0, 4, endpoint=False)
        w, h = c.width - 0.5, c.height - 0.5
        u = np.concatenate([-0.5 + f * c.width, np.full(4, w), w - f * c.width, np.full(4, -0.5)])
        v = np.concatenate([np.full(4, -0.5), -0.5 + f * c.height, np.full(4, h), h - f * c.height])
        n = self.camera.normalised_from_raw_px(
            np.column_stack([u, v]), criteria=RENDER_UNDISTORT_CRITERIA
        )
        d = np.column_stack([n, np.ones(len(n))]) @ pose.R.T
        t = (z_ground - pose.C[2]) / d[:, 2]
        return pose.C[:2] + t[:, None] * d[:, :2]

    def render(self, pose: Pose) -> FrameRender:
        c = self.world.cfg
        C = pose.C
        z_ground = float(self.world.base(np.array(C[0]), np.array(C[1])))
        fp = self.footprint(pose, z_ground)
        pad = 0.12 + 0.05 * (C[2] - z_ground)
        H, Rm, D, mx0, my0 = self._mosaic(
            fp[:, 0].min() - pad, fp[:, 1].min() - pad, fp[:, 0].max() + pad, fp[:, 1].max() + pad
        )
        g = self.g
        d = (self.rays_cam @ pose.R.T.astype(np.float32)).astype(np.float32)  # world directions
        inv_dz = np.float32(1.0) / d[..., 2]
        # Mosaic pixel coordinates are affine in the ray parameter t (z-depth, since ray z = 1).
        col0 = np.float32((C[0] - mx0) / g - 0.5)
        row0 = np.float32((my0 - C[1]) / g - 0.5)
        dcol = d[..., 0] / np.float32(g)
        drow = -d[..., 1] / np.float32(g)
        Hrel = H - np.float32(C[2])  # heights relative to the camera (small numbers, float32)
        # Start on the plane under the camera; fixed-point iterations on the height field.
        t = np.float32(z_ground - C[2]) * inv_dz
        for _ in range(max(1, c.raycast_iters)):
            zh = cv2.remap(
                Hrel,
                col0 + t * dcol,
                row0 + t * drow,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
            t = zh * inv_dz
        col = col0 + t * dcol
        row = row0 + t * drow
        rad = cv2.remap(Rm, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        dep = cv2.remap(D, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if self.ss > 1:
            rad = cv2.resize(rad, (c.width, c.height), interpolation=cv2.INTER_AREA)
        # Ground area seen by each ray (z-depth t, focal fx, 1/ss^2 of a pixel).
        cell = (t / c.fx) ** 2 / (self.ss * self.ss)
        deep = dep > 0.010
        area = float(np.sum(cell[deep]))
        return FrameRender(rad, area, float(dep.max()) if dep.size else 0.0, fp)
