"""Pixels that stay the same in every frame: a burned-in stamp or the bonnet no mask names.

A camera on a moving vehicle sees a different stretch of road in every frame, so every road
pixel changes between frames taken metres apart. Pixels that do not change (the temporal
standard deviation over frames spread along the drive at the level of the sensor's noise,
far below the road's own) show something fixed to the camera. The stages' checks refuse most
of what those pixels give (they match with no motion), but the mosaic paints them along the
whole drive and some features and dark regions come from them, so ``roadsurf run`` warns and
writes a suggested mask (camera.yaml ``mask``, docs/formats.md) for the user to check.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from roadsurf.core.errors import FrameReadError
from roadsurf.io.drive.images import read_gray
from roadsurf.io.drive.types import Frame

log = logging.getLogger(__name__)

N_FRAMES = 12  # frames sampled, evenly over the drive (count)
MIN_FRAMES = 6  # below this many readable frames the test says nothing (count)
WORK_PX = 320  # the frames are compared at this width (px): the test is about regions
# a pixel is static when its temporal σ is below max(STATIC_DN, STATIC_REL x the image's
# median temporal σ): sensor noise is 1-3 DN, a road pixel's σ over different stretches of
# road is its texture's contrast (10-40 DN on asphalt)
STATIC_DN = 3.0
STATIC_REL = 0.15
# ... and only where the road does vary: an image whose median σ is below this (DN) is a
# stopped vehicle or a textureless road, where nothing can be told apart
MIN_MEDIAN_DN = 6.0
MIN_REGION_SHARE = 0.002  # static regions smaller than this share of the image are noise (−)
WARN_SHARE = 0.005  # warn when the static regions cover more than this share (−)


@dataclass(frozen=True)
class StaticPixels:
    """Where the sampled frames did not change."""

    static: np.ndarray  # (height, width) bool at the camera's size: True = the same every frame
    share: float  # share of the image that is static (0-1)
    n_frames: int  # frames compared
    median_sigma_dn: float  # the image's median temporal σ (DN)

    def suggested_mask(self) -> np.ndarray:
        """(height, width) uint8 in camera.yaml's mask convention: 0 = ignore (the static
        regions grown by 3 px), 255 = road."""
        grown = cv2.dilate(self.static.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
        return np.where(grown, 0, 255).astype(np.uint8)

    def warning(self, mask_path: str) -> str:
        ys, xs = np.nonzero(self.static)
        return (
            f"{self.share:.1%} of the image is the same in all {self.n_frames} frames compared "
            f"(rows {ys.min()}-{ys.max()}, columns {xs.min()}-{xs.max()}): something fixed to "
            "the camera (a burned-in stamp, the bonnet) that the mosaic paints along the whole "
            f"drive. A suggested mask is in {mask_path}: check it and name it in camera.yaml "
            "('mask', docs/formats.md)."
        )


def static_pixels(frames: list[Frame], width: int, height: int) -> StaticPixels | None:
    """The static pixels of ``frames`` (a camera of ``width`` x ``height``), from up to
    ``N_FRAMES`` frames spread over the drive; None when the drive cannot tell (too few
    readable frames, a road that does not vary)."""
    if len(frames) < MIN_FRAMES:
        return None
    pick = np.unique(np.linspace(0, len(frames) - 1, min(N_FRAMES, len(frames))).round())
    s = min(1.0, WORK_PX / width)
    size = (max(1, round(width * s)), max(1, round(height * s)))
    stack = []
    for i in pick.astype(int):
        try:
            g = read_gray(frames[i])
        except FrameReadError as e:
            log.debug("static pixels: %s skipped (%s)", frames[i].filename, e)
            continue
        if g.shape != (height, width):
            continue
        stack.append(cv2.resize(g, size, interpolation=cv2.INTER_AREA).astype(np.float32))
    if len(stack) < MIN_FRAMES:
        return None
    sd = np.std(np.stack(stack), axis=0)
    med = float(np.median(sd))
    if med < MIN_MEDIAN_DN:
        return None
    small = (sd < max(STATIC_DN, STATIC_REL * med)).astype(np.uint8)
    # isolated pixels are chance; a stamp's changing digits are holes in its static box
    small = cv2.morphologyEx(small, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    small = cv2.morphologyEx(small, cv2.MORPH_CLOSE, np.ones((7, 7), np.uint8))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(small, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= MIN_REGION_SHARE * small.size
    small = keep[lab].astype(np.uint8)
    static = cv2.resize(small, (width, height), interpolation=cv2.INTER_NEAREST) > 0
    return StaticPixels(static, float(static.mean()), len(stack), med)
