"""The RGB orthomosaic of one tile: every frame seeing it projected onto the fitted road
(plus the residual) and blended with feathered weights, from a small shared image cache."""

from __future__ import annotations

import logging

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.errors import FrameReadError
from roadsurf.core.parallel import SharedCache
from roadsurf.core.rolling import frame_motion, raw_px_from_world
from roadsurf.io.drive import Frame, read_image
from roadsurf.io.formats import GridSpec
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.raster import GridToEnu, TileLattice
from roadsurf.mapping.surface import LocalSurface
from roadsurf.mapping.types import Trajectory

log = logging.getLogger(__name__)


class ImageCache:
    """A few decoded (and pyramid-reduced) images, shared by the tile threads; tiles are
    visited in drive order."""

    def __init__(self, size: int = 12) -> None:
        self._c: SharedCache[tuple[str, int], np.ndarray | None] = SharedCache(size)

    def get(self, frame: Frame, level: int) -> np.ndarray | None:
        def load() -> np.ndarray | None:
            try:
                img = read_image(frame)
                for _ in range(level):
                    img = cv2.pyrDown(img)
                return img
            except (FrameReadError, OSError) as e:
                log.warning("globalmap: %s not used in the mosaic (%s)", frame.filename, e)
                return None

        return self._c.get((frame.filename, level), load)


def mosaic_tile(
    cfg: MappingConfig,
    cam: Camera,
    traj: Trajectory,
    surf: LocalSurface,
    g2e: GridToEnu,
    grid: GridSpec,
    t: tuple[int, int],
    lat: TileLattice,
    fbox: list[tuple[int, int, int, int] | None],
    frame_ids: list[int],
    frame_list: list[Frame | None],
    res_t: np.ndarray,
    road_z: np.ndarray,
    cache: ImageCache,
    level: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Project the frames seeing tile t onto the fitted road (+ residual) and blend them with
    feathered weights. Returns (H, W, 3) uint8 (0 = nodata) and the weight sum (H, W)."""
    tp = lat.tile_px
    acc = np.zeros((tp, tp, 3), np.float32)
    wsum = np.zeros((tp, tp), np.float32)
    if not frame_ids:
        return acc.astype(np.uint8), wsum
    # union of the footprint windows inside this tile
    boxes = []
    for i in frame_ids:
        b = fbox[i]
        r0, r1 = max(b[0] - t[0] * tp, 0), min(b[1] - t[0] * tp, tp - 1)
        c0, c1 = max(b[2] - t[1] * tp, 0), min(b[3] - t[1] * tp, tp - 1)
        boxes.append((r0, r1, c0, c1) if r1 >= r0 and c1 >= c0 else None)
    valid = [b for b in boxes if b is not None]
    if not valid:
        return acc.astype(np.uint8), wsum
    R0, R1 = min(b[0] for b in valid), max(b[1] for b in valid)
    C0, C1 = min(b[2] for b in valid), max(b[3] for b in valid)
    e, n = g2e.pixel_enu(grid, slice(R0, R1 + 1), slice(C0, C1 + 1))
    # the fitted road is smooth on the node scale (25 cm): evaluate it every 8 px and upsample
    zs = surf.height(np.column_stack([e[::8, ::8].ravel(), n[::8, ::8].ravel()]))
    zs = zs.reshape(e[::8, ::8].shape).astype(np.float32)
    if np.isfinite(zs).any():
        zs = np.where(np.isfinite(zs), zs, np.nanmedian(zs))
    z = cv2.resize(zs, (e.shape[1], e.shape[0]), interpolation=cv2.INTER_LINEAR).astype(float)
    rz = res_t[R0 : R1 + 1, C0 : C1 + 1]
    z = z + np.where(np.isfinite(rz), rz, 0.0)
    scale = 0.5**level
    border = cfg.mosaic_border_px
    feather = max(cfg.feather_px, 1)
    for i, b in zip(frame_ids, boxes, strict=True):
        fr = frame_list[i]
        if b is None or fr is None:
            continue
        img = cache.get(fr, level)
        if img is None:
            continue
        r0, r1, c0, c1 = b
        sl = (slice(r0 - R0, r1 - R0 + 1), slice(c0 - C0, c1 - C0 + 1))
        zz = z[sl]
        zz = np.where(np.isfinite(zz), zz, road_z[i])
        W = traj.world_from_cam[i]
        if cam.readout_s > 0:  # each row has its own pose: the frame's is its first row's
            vel, om = frame_motion(traj.world_from_cam, traj.timestamp_s, i, traj.segment)
            u, v = raw_px_from_world(cam, np.stack([e[sl], n[sl], zz], axis=-1), W, vel, om)
        else:
            X = np.stack([e[sl] - W[0, 3], n[sl] - W[1, 3], zz - W[2, 3]], axis=-1)
            u, v = cam.project(X @ W[:3, :3])  # R^T (X - c), row-vector form
        d = np.minimum.reduce(
            [u - border, cam.width - 1 - border - u, v - border, cam.height - 1 - border - v]
        )
        if cam.mask is not None:  # feathered off the camera's mask as off the image border
            d = np.minimum(d, cam.mask.clearance_at(u, v) - 1.0 - border)
        w = np.clip(d / feather, 0.0, 1.0)
        w = np.where(np.isfinite(w), w, 0.0).astype(np.float32) ** 2
        if not (w > 0).any():
            continue
        # pixel centre convention: full-res (u, v) -> level-l ((u + 0.5) * s - 0.5)
        mx = ((np.nan_to_num(u, nan=-1e4) + 0.5) * scale - 0.5).astype(np.float32)
        my = ((np.nan_to_num(v, nan=-1e4) + 0.5) * scale - 0.5).astype(np.float32)
        # replicate: with mosaic_border_px = 0 the outermost half pixel must not blend in black
        samp = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        tile_sl = (slice(r0, r1 + 1), slice(c0, c1 + 1))
        acc[tile_sl] += samp.astype(np.float32) * w[..., None]
        wsum[tile_sl] += w
    out = np.zeros((tp, tp, 3), np.uint8)
    has = wsum > 0
    out[has] = np.clip(np.round(acc[has] / wsum[has, None]), 1, 255).astype(np.uint8)
    return out, wsum
