"""Image-fixed overlays of a dash or survey camera (docs/simulator.md, *Image-fixed overlays*).

Two things stay put in the image while the road moves under them:

- ``overlay_text``: a burned-in date/time/speed stamp, an opaque black box with white text in
  the top-left corner. The box never moves; its text is the frame's time and speed.
- ``hood_share``: the vehicle's bonnet along the bottom edge, a dark, slightly reflective grey
  region under a gentle curve (highest at the image centre). The same pixel values in every
  frame: it is drawn after the sensor model, without noise, exposure jitter or vignetting.

Both are drawn onto the final 8-bit image just before encoding (a burned-in overlay is not
affected by the sensor). ``overlay_mask`` is the COLMAP/OpenSfM image mask of them: 0 on the
overlay pixels dilated by ``MASK_DILATE_PX``, 255 elsewhere.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from roadsurf.core.atomic import write_bytes_atomic
from roadsurf.io import drivefolder as df
from roadsurf.simulation.config import SimConfig

MASK_NAME = df.MASK_PNG  # the mask's file name beside camera.yaml and in truth/
MASK_DILATE_PX = 2  # the mask's 0 region reaches this far beyond the overlay pixels (px)
BOX_WIDTH_SHARE = 0.35  # the text box's width / image width (-)
BOX_HEIGHT_SHARE = 0.06  # the text box's height / image height (-)
BOX_MIN_HEIGHT_PX = 12  # smallest text box height (px)
BOX_MARGIN_SHARE = 0.015  # gap between the box and the image's top and left edges / height (-)
HOOD_SIDE_DROP = 0.3  # the hood edge at the image sides lies this share of its centre height
# lower (-): (1 - HOOD_SIDE_DROP) * hood_share * height above the bottom edge
_FONT = cv2.FONT_HERSHEY_SIMPLEX
MIN_FONT_SCALE = 0.3  # smallest cv2 font scale (-): ~7 px high digits, still legible


def has_overlay(cfg: SimConfig) -> bool:
    """True when the frames carry any image-fixed overlay."""
    return bool(cfg.overlay_text or cfg.hood_share > 0.0)


def text_box_px(width: int, height: int) -> tuple[int, int, int, int]:
    """The stamp box (x0, y0, x1, y1) in pixels, x1 and y1 exclusive, for a width x height image."""
    margin = int(round(BOX_MARGIN_SHARE * height))
    bh = min(max(BOX_MIN_HEIGHT_PX, int(round(BOX_HEIGHT_SHARE * height))), height - margin)
    bw = min(max(4 * bh, int(round(BOX_WIDTH_SHARE * width))), width - margin)
    return margin, margin, margin + bw, margin + bh


def stamp_text(cfg: SimConfig, t_s: float, speed_mps: float, style: int = 0) -> str:
    """The stamp of a frame at ``t_s`` seconds after ``start_utc`` at ``speed_mps`` (the clock
    of start_utc's own time zone). ``style`` 0: ``2026-06-15 14:00:02.00  22 km/h``; 1 (a
    narrower box): ``14:00:02.00  22 km/h``; 2: ``14:00:02.00``."""
    when = datetime.fromisoformat(cfg.start_utc) + timedelta(seconds=float(t_s))
    cs = min(int(when.microsecond // 10_000), 99)
    clock = f"{when:%H:%M:%S}.{cs:02d}"
    speed = f" {round(3.6 * speed_mps):3d} km/h"
    return (f"{when:%Y-%m-%d} {clock}{speed}", f"{clock}{speed}", clock)[style]


# the widest text of each stamp style (100 km/h; digits are equally wide in this font)
_SAMPLES = ("2026-06-15 14:00:02.00 100 km/h", "14:00:02.00 100 km/h", "14:00:02.00")


@lru_cache(maxsize=8)
def _font(box_w: int, box_h: int) -> tuple[int, float, int, int, int]:
    """(style, scale, thickness, x, baseline y) of the stamp: the longest style whose text
    fits the box (at most 70 % of its height and 94 % of its width) at a font scale of at
    least MIN_FONT_SCALE, else the shortest, cut off at the box's inner edge."""
    scales = []
    for sample in _SAMPLES:
        (w1, h1), b1 = cv2.getTextSize(sample, _FONT, 1.0, 1)
        scales.append(min(0.7 * box_h / (h1 + b1), 0.94 * box_w / w1))
    style = next((i for i, sc in enumerate(scales) if sc >= MIN_FONT_SCALE), len(scales) - 1)
    sample = _SAMPLES[style]
    scale = max(scales[style], MIN_FONT_SCALE)
    thick = max(1, int(round(scale * 1.6)))
    (w, h), b = cv2.getTextSize(sample, _FONT, scale, thick)
    x = max(2, (box_w - w) // 2)
    y = int(round((box_h + h - b) / 2))
    return style, scale, thick, x, y


def hood_edge_px(width: int, height: int, share: float) -> np.ndarray:
    """(W,) float64 image row of the hood's top edge in each column (pixel-centre convention:
    a pixel belongs to the hood when its centre lies below the edge)."""
    x = (np.arange(width) - (width - 1) / 2.0) / (width / 2.0)  # -1 .. 1 across
    return height - 0.5 - share * height * (1.0 - HOOD_SIDE_DROP * x * x)


@lru_cache(maxsize=4)
def _hood(width: int, height: int, share: float, grey: bool) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) bool hood pixels and its uint8 look, (H, W, 3) RGB or (H, W) grey: dark
    blue-grey paint (~35 DN), a soft sky reflection (+25 DN) just below the edge and a broad
    darkening towards the sides; smooth and static."""
    edge = hood_edge_px(width, height, share)
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    inside = vv > edge[None, :]
    depth = np.maximum(height - 0.5 - edge, 1.0)[None, :]
    s = np.clip((vv - edge[None, :]) / depth, 0.0, 1.0)  # 0 at the edge, 1 at the bottom
    x = (uu - (width - 1) / 2.0) / (width / 2.0)
    grey_dn = (30.0 + 8.0 * (1.0 - s) + 25.0 * np.exp(-(((s - 0.15) / 0.1) ** 2))) * (
        1.0 - 0.25 * x * x
    )
    tint = np.array([0.92, 0.97, 1.06])  # RGB: slightly blue paint
    rgb = np.clip(np.rint(grey_dn[..., None] * tint), 0, 255).astype(np.uint8)
    look = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if grey else rgb
    return inside, look


def overlay_pixels(cfg: SimConfig) -> np.ndarray:
    """(H, W) bool: the pixels any overlay covers (the whole stamp box, the hood)."""
    px = np.zeros((cfg.height, cfg.width), bool)
    if cfg.hood_share > 0.0:
        px |= _hood(cfg.width, cfg.height, float(cfg.hood_share), cfg.greyscale)[0]
    if cfg.overlay_text:
        x0, y0, x1, y1 = text_box_px(cfg.width, cfg.height)
        px[y0:y1, x0:x1] = True
    return px


def overlay_mask(cfg: SimConfig) -> np.ndarray:
    """(H, W) uint8 image mask: 0 on the overlay pixels dilated by MASK_DILATE_PX (a square
    neighbourhood), 255 on usable pixels (COLMAP/OpenSfM convention)."""
    k = 2 * MASK_DILATE_PX + 1
    covered = cv2.dilate(overlay_pixels(cfg).astype(np.uint8), np.ones((k, k), np.uint8))
    return np.where(covered > 0, 0, 255).astype(np.uint8)


def apply_overlay(img: np.ndarray, cfg: SimConfig, t_s: float, speed_mps: float) -> np.ndarray:
    """Draw the overlays onto a final uint8 frame (H, W, 3) RGB or (H, W) grey; ``t_s``: the
    frame's time after start_utc (s), ``speed_mps``: the vehicle's speed (m/s) for the stamp.
    Returns ``img`` itself when no overlay is on, otherwise a new array."""
    if not has_overlay(cfg):
        return img
    out = img.copy()
    if cfg.hood_share > 0.0:
        inside, look = _hood(cfg.width, cfg.height, float(cfg.hood_share), out.ndim == 2)
        out[inside] = look[inside]
    if cfg.overlay_text:
        x0, y0, x1, y1 = text_box_px(cfg.width, cfg.height)
        box = np.zeros((y1 - y0, x1 - x0) + out.shape[2:], np.uint8)
        style, scale, thick, x, y = _font(x1 - x0, y1 - y0)
        white = (255,) * (1 if out.ndim == 2 else 3)
        text = stamp_text(cfg, t_s, speed_mps, style)
        inner = np.zeros_like(box[1:-1, 1:-1])  # a black border of 1 px stays around the text
        cv2.putText(inner, text, (x - 1, y - 1), _FONT, scale, white, thick, cv2.LINE_AA)
        box[1:-1, 1:-1] = inner
        out[y0:y1, x0:x1] = box  # drawn in its own array: nothing leaks out of the box
    return out


def write_masks(cfg: SimConfig, out: Path) -> None:
    """out/truth/mask.png with any overlay; out/mask.png with ``write_mask`` (all 255 when
    no overlay is on: a valid mask that ignores nothing)."""
    if not (has_overlay(cfg) or cfg.write_mask):
        return
    ok, buf = cv2.imencode(".png", overlay_mask(cfg), [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise RuntimeError("OpenCV failed to encode the image mask")
    if has_overlay(cfg):
        (out / df.TRUTH_DIR).mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(out / df.TRUTH_DIR / MASK_NAME, buf.tobytes())
    if cfg.write_mask:
        write_bytes_atomic(out / MASK_NAME, buf.tobytes())
