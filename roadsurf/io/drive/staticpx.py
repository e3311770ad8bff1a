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

import dataclasses
import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from roadsurf.core.errors import FrameReadError
from roadsurf.core.imagemask import ImageMask
from roadsurf.io.drive.images import read_gray
from roadsurf.io.drive.types import Drive, Frame

log = logging.getLogger(__name__)

N_FRAMES = 12  # frames sampled, evenly over the drive (count)
MIN_FRAMES = 6  # below this many readable frames the test says nothing (count) ...
MIN_BORDER_FRAMES = 2  # ... but a black border is told from two (a photo pair's)
# the σ map is judged at this width (px): the test is about regions; σ itself is taken at full
# resolution first (downscaling the frames would average a fine road grain to "static")
WORK_PX = 640
# a pixel is static when its temporal σ is below max(STATIC_DN, STATIC_REL x the image's
# median temporal σ): sensor noise is 1-3 DN, a road pixel's σ over different stretches of
# road is its texture's contrast (10-40 DN on asphalt)
STATIC_DN = 3.0
STATIC_REL = 0.15
# ... and only where the road does vary: an image whose median σ is below this (DN) is a
# stopped vehicle or a textureless road, where nothing can be told apart
MIN_MEDIAN_DN = 6.0
SATURATED_DN = 250  # at or above this in every frame: over-exposed (sky), not a stamp (DN)
# at or below this in every frame, and reaching the image's edge: no image there (a letterbox,
# the black edges undistortion leaves, a fisheye's corners), not road (DN; JPEG rings to ~10)
BLACK_DN = 12
# static regions smaller than this share of the image are noise (−): a one-line text stamp
# without a box is ~0.4 % of a 1280 x 720 frame, a stuck pixel or dust far below
MIN_REGION_SHARE = 0.002
GROUP_PX = 15  # static pieces this close on the work grid form one region (px at WORK_PX)


@dataclass(frozen=True)
class StaticPixels:
    """Where the sampled frames did not change."""

    static: np.ndarray  # (height, width) bool at the camera's size: True = the same every frame
    saturated: np.ndarray  # (height, width) bool: ... of them, over-exposed in every frame
    n_frames: int  # frames compared
    grow_px: int  # the suggested mask grows the regions by this (px): the work grid's pixel + 3
    # (height, width) bool: black in every frame and reaching the image's edge (``BLACK_DN``);
    # left out of ``static`` (the pipeline masks it: no image there); empty: none found
    black_border: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))

    @property
    def share(self) -> float:
        """Share of the image that is static (0-1)."""
        return float(self.static.mean())

    def outside(self, usable: np.ndarray) -> StaticPixels:
        """The static pixels within ``usable`` (a camera mask's usable pixels) only."""
        keep = usable & self.static
        return StaticPixels(
            keep, keep & self.saturated, self.n_frames, self.grow_px, self.black_border
        )

    def suggested_mask(self) -> np.ndarray:
        """(height, width) uint8 in camera.yaml's mask convention: 0 = ignore (the static
        regions grown by ``grow_px``), 255 = road."""
        k = 2 * self.grow_px + 1
        grown = cv2.dilate(self.static.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
        return np.where(grown, 0, 255).astype(np.uint8)

    def warning(self, mask_path: str, outside_mask: bool = False) -> str:
        ys, xs = np.nonzero(self.static)
        where = " outside camera.yaml's mask" if outside_mask else ""
        sat = float(self.saturated.mean())
        what = "something fixed to the camera (a burned-in stamp, the bonnet)"
        if sat > 0.5 * self.share:  # (a stamp's white letters are over-exposed too)
            what = "mostly pixels over-exposed in every frame (sky, glare)"
        return (
            f"{self.share:.1%} of the image{where} is the same in all {self.n_frames} frames "
            f"compared (rows {ys.min()}-{ys.max()}, columns {xs.min()}-{xs.max()}): {what}, "
            "which the mosaic paints along the whole drive. A suggested mask is in "
            f"{mask_path}: check it and name it in camera.yaml ('mask', docs/formats.md)."
        )


def static_pixels(
    frames: list[Frame], width: int, height: int, usable: np.ndarray | None = None
) -> StaticPixels | None:
    """The static pixels of ``frames`` (a camera of ``width`` x ``height``), from up to
    ``N_FRAMES`` frames spread over the drive, among the ``usable`` ones (camera.yaml's mask,
    (height, width) bool; None = all) and apart from a black border (``black_border``, told
    from ``MIN_BORDER_FRAMES``: with fewer than ``MIN_FRAMES`` no pixel is called static);
    None when the drive cannot tell (too few readable frames, a road that does not vary)."""
    if len(frames) < MIN_BORDER_FRAMES:
        return None
    pick = np.unique(np.linspace(0, len(frames) - 1, min(N_FRAMES, len(frames))).round())
    s1 = np.zeros((height, width), np.float64)
    s2 = np.zeros((height, width), np.float64)
    lo = np.full((height, width), 255, np.uint8)
    hi = np.zeros((height, width), np.uint8)
    n = 0
    for i in pick.astype(int):
        try:
            g = read_gray(frames[i])
        except FrameReadError as e:
            log.debug("static pixels: %s skipped (%s)", frames[i].filename, e)
            continue
        if g.shape != (height, width):
            continue
        s1 += g
        s2 += np.square(g, dtype=np.float64)
        np.minimum(lo, g, out=lo)
        np.maximum(hi, g, out=hi)
        n += 1
    if n < MIN_BORDER_FRAMES:
        return None
    sd = np.sqrt(np.maximum(s2 / n - np.square(s1 / n), 0.0)).astype(np.float32)
    inside = np.ones((height, width), bool) if usable is None else np.asarray(usable, bool)
    border = _black_border(hi, inside)
    inside = inside & ~border
    none = np.zeros((height, width), bool)
    if n < MIN_FRAMES or not inside.any():  # too few frames to tell a stamp: the border only
        return StaticPixels(none, none, n, 0, border) if border.any() else None
    med = float(np.median(sd[inside]))
    if med < MIN_MEDIAN_DN:
        return None
    # judged per full-resolution pixel (a stamp's strokes are a few pixels wide), then a work
    # pixel is static when any of its pixels is; what a mask or the border leaves out is not
    # judged (a ring round the image would enclose, and fill, everything)
    low = ((sd < max(STATIC_DN, STATIC_REL * med)) & inside).astype(np.float32)
    s = min(1.0, WORK_PX / width)
    size = (max(1, round(width * s)), max(1, round(height * s)))
    if s < 1:
        low = np.asarray(cv2.resize(low, size, interpolation=cv2.INTER_AREA), np.float32)
    # a text stamp's strokes merge into one region, and what a static region encloses (the
    # changing digits inside a stamp's box) belongs to it; isolated pixels, chance, go
    closed = cv2.morphologyEx(
        (low > 0).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)
    )
    small = _fill_holes(
        np.asarray(cv2.morphologyEx(closed, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)))
    )
    # regions are judged by their group: pieces within GROUP_PX of each other (the words of a
    # stamp's line) count together
    groups = cv2.dilate(small, np.ones((GROUP_PX, GROUP_PX), np.uint8))
    count, lab = cv2.connectedComponents(groups, connectivity=8)
    area = np.bincount(lab[small > 0], minlength=count)
    keep = area >= MIN_REGION_SHARE * small.size
    keep[0] = False
    small = (keep[lab] & (small > 0)).astype(np.uint8)
    static = cv2.resize(small, (width, height), interpolation=cv2.INTER_NEAREST) > 0
    saturated = static & (lo >= SATURATED_DN)
    return StaticPixels(static, saturated, n, int(np.ceil(1.0 / s)) + 3, border)


def _black_border(hi: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """(h, w) bool: the usable pixels at or below ``BLACK_DN`` in every frame (``hi``, their
    maximum) in regions that reach the image's edge and hold ``MIN_REGION_SHARE`` of it."""
    dark = ((hi <= BLACK_DN) & usable).astype(np.uint8)
    count, lab, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)
    h, w = dark.shape
    x, y, bw, bh, area = (stats[:, k] for k in range(5))
    edge = (x == 0) | (y == 0) | (x + bw == w) | (y + bh == h)
    keep = edge & (area >= MIN_REGION_SHARE * dark.size)
    keep[0] = False
    return np.asarray(keep[lab] & (dark > 0))


# a hole a static region encloses joins it up to this share of the image (−): a stamp box's
# changing digits (~1 %), not the whole road inside a static ring along the image's edges
MAX_HOLE_SHARE = 0.05


def _fill_holes(region: np.ndarray) -> np.ndarray:
    """(h, w) uint8 0/1 ``region`` with the background it encloses (not connected to the
    image border) added, each hole up to ``MAX_HOLE_SHARE`` of the image."""
    h, w = region.shape
    pad = np.zeros((h + 2, w + 2), np.uint8)
    pad[1:-1, 1:-1] = region
    flood = pad.copy()
    cv2.floodFill(flood, np.zeros((h + 4, w + 4), np.uint8), (0, 0), 1)
    holes = (flood[1:-1, 1:-1] == 0).astype(np.uint8)
    count, lab, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=4)
    small = stats[:, cv2.CC_STAT_AREA] <= MAX_HOLE_SHARE * h * w
    small[0] = False
    return np.asarray(region | small[lab], np.uint8)


def static_pixels_of_drive(drive: Drive) -> StaticPixels | None:
    """``static_pixels`` of the drive's frames within camera.yaml's mask; a black border found
    there joins ``drive.camera``'s mask, with a warning in ``drive.warnings`` (every stage and
    the classifier's thumbnails then see the same pixels).

    A black border in every frame (a letterbox, the edges undistortion leaves) is no image.
    Its corners are the same in every frame, so they matched shots of different places with
    no motion, and a pair failing between them no longer kept the two apart (real
    photographs: two potholes on one spot of the map, a crack along the image's top edge)."""
    cam = drive.camera
    usable = cam.mask.usable if cam.mask is not None else None
    sp = static_pixels(drive.frames, cam.width, cam.height, usable)
    if sp is None or not sp.black_border.any():
        return sp
    border = sp.black_border
    usable = ~border if cam.mask is None else cam.mask.usable & ~border
    src = f"{cam.mask.source} + " if cam.mask is not None else ""
    mask = ImageMask(usable, f"{src}black border found in every frame")
    drive.camera = dataclasses.replace(cam, mask=mask)
    msg = (
        f"{border.mean():.1%} of the image is black in every frame along its edges: no image "
        "there (a letterbox, the edges undistortion leaves); left out as camera.yaml's mask "
        "would. Name it in camera.yaml's mask (docs/formats.md) to say so yourself."
    )
    log.warning(msg)
    drive.warnings.append(msg)
    return sp
