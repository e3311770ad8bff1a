"""The pair's images on image a's ideal pixel grid (image b through the road homography), and the
part of that grid the matching works on (``reconstruction.dense.parallax``).

The grid may be padded beyond image a's border: image a has no pixels there (its mask is 0, so
no window uses them), but image b may. A forward-tilted camera moving forward sees, in the next
frame, the road beyond the top of image a; a pixel in image a's top rows whose parallax points
up samples image b above row 0, and without the padding its own sample read as outside image b
(45° pitch, a pair of the tilted drive: 514 of the 2,140 overlap pixels without a height lay in
image a's top 4 rows, the far field, ~12 mm of road per pixel along the track).
"""

from __future__ import annotations

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.geometry import PlaneParallax
from roadsurf.reconstruction.dense.rolling import baseline_share, raw_px_from_plane_px


def resample_pair(
    img_a: np.ndarray,
    img_b: np.ndarray,
    camera: Camera,
    H: np.ndarray,
    s: float,
    rs: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None,
    pad: int = 0,
    share: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Image a on its ideal pixel grid resized by ``s``, image b through H onto the same grid
    (float32 DN), and where each sample lies inside its image and off the camera's mask
    (bool). ``rs`` = (R, t, plane, frame_dt_s): a rolling shutter, each grid pixel read from
    the rows that saw its road point (``dense.rolling``) instead of through H at the
    timestamps. ``pad`` (px): the grid reaches that far beyond the work grid on every side (its
    pixel (pad, pad) is the work grid's (0, 0); (h + 2 pad, w + 2 pad) arrays). ``share``: with
    ``rs``, a list that gets each grid pixel's baseline share s_b - s_a
    (``dense.rolling.baseline_share``, NaN where a frame's row is unknown) appended."""
    W, Hh = camera.width, camera.height
    w, h = int(round(W * s)), int(round(Hh * s))
    # a sample whose cubic kernel (2 px) or anti-aliasing blur (2 σ) reaches a masked raw pixel
    # is not a road sample: it counts as outside its image
    mask_margin = 2.0
    if s < 1.0:  # anti-aliasing before the resampling
        sig = 0.5 * np.sqrt(1.0 / (s * s) - 1.0)
        mask_margin += 2.0 * sig
        img_a = cv2.GaussianBlur(img_a, (0, 0), sig)
        img_b = cv2.GaussianBlur(img_b, (0, 0), sig)
    v, u = np.mgrid[-pad : h + pad, -pad : w + pad].astype(np.float64)
    h, w = u.shape
    u, v = (u + 0.5) / s - 0.5, (v + 0.5) / s - 0.5
    q = np.stack([u, v, np.ones_like(u)], -1) @ H.T
    ub, vb = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
    if rs is not None:
        R, t, plane, dt = rs
        ua, va = raw_px_from_plane_px(u, v, camera, R, t, plane, dt, 0)
        ub, vb = raw_px_from_plane_px(u, v, camera, R, t, plane, dt, 1)
        if share is not None:
            share.append(baseline_share(va, vb, camera, dt))
        ua, va, ub, vb = (np.nan_to_num(x, nan=-10.0) for x in (ua, va, ub, vb))
    elif camera.has_distortion:
        ra = camera.distort_px(np.column_stack([u.ravel(), v.ravel()])).reshape(h, w, 2)
        rb = camera.distort_px(np.column_stack([ub.ravel(), vb.ravel()])).reshape(h, w, 2)
        ua, va, ub, vb = ra[..., 0], ra[..., 1], rb[..., 0], rb[..., 1]
    else:
        ua, va = u, v

    def remap(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = cv2.remap(
            img.astype(np.float32),
            x.astype(np.float32),
            y.astype(np.float32),
            cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_REPLICATE,
        )
        inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= Hh - 1)
        return out, inside

    A, mA = remap(img_a, ua, va)
    B, mB = remap(img_b, ub, vb)
    if camera.mask is not None:
        mA &= camera.mask.usable_grid(ua, va, mask_margin)
        mB &= camera.mask.usable_grid(ub, vb, mask_margin)
    return A, B, mA, mB


def reach_px(pp: PlaneParallax, cfg: DenseHeightConfig, h: int, w: int) -> int:
    """How far (px) a match may sample from its pixel on the h x w grid of ``pp``: the largest
    parallax of the searched height range (on a 9 x 9 lattice of the grid), a window and 2 px."""
    v, u = np.mgrid[0 : h : max(h // 8, 1), 0 : w : max(w // 8, 1)].astype(float)
    reach = np.abs(
        np.concatenate(
            [
                pp.shift_from_height(np.full(u.shape, e), u, v).ravel()
                for e in (-cfg.max_depth_m, cfg.max_height_m)
            ]
        )
    )
    reach = reach[np.isfinite(reach)]
    return int(np.ceil(reach.max() if len(reach) else 0.0)) + int(cfg.window_px) + 2


def overlap_crop(
    seen: np.ndarray, pad: int, cfg: DenseHeightConfig
) -> tuple[int, int, int, int] | None:
    """Rows r0:r1 and columns c0:c1 of the grid holding the pixels ``seen`` (image a's pixels
    whose road lies inside image b), widened by ``pad`` px (``reach_px``); None when there are
    none."""
    rows = np.flatnonzero(seen.any(axis=1))
    cols = np.flatnonzero(seen.any(axis=0))
    if len(rows) == 0 or len(cols) == 0:
        return None
    h, w = seen.shape
    r0, r1 = max(int(rows[0]) - pad, 0), min(int(rows[-1]) + 1 + pad, h)
    c0, c1 = max(int(cols[0]) - pad, 0), min(int(cols[-1]) + 1 + pad, w)
    if r1 - r0 < 2 * cfg.window_px or c1 - c0 < 2 * cfg.window_px:
        return None
    return r0, r1, c0, c1
