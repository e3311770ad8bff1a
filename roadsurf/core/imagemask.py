"""The camera's image mask: pixels that never show the road.

Real vehicle cameras see things that stay fixed in the image while the road moves under them:
a burned-in date/time stamp, the bonnet along the bottom edge, a bracket or a wiper at rest.
They match themselves perfectly between frames (zero motion, whatever the road does), so a
feature, a dense window or a 2D defect candidate on them is wrong. camera.yaml's ``mask``
names an 8-bit image of the camera's size whose 0 pixels are to be ignored (COLMAP's and
OpenSfM's convention); every stage that reads pixels asks this object which it may use.

Pure arrays, no file access (``roadsurf.io.drive.maskfile`` reads the file).
"""

from __future__ import annotations

import hashlib
from functools import cached_property

import cv2
import numpy as np


class ImageMask:
    """(height, width) usable pixels of a camera's raw images (True = shows the road).

    Compared and hashed by ``digest`` (16 hex digits over the pixels and the size), which the
    stage fingerprints take: a changed mask recomputes what it touches."""

    def __init__(self, usable: np.ndarray, source: str = "") -> None:
        u = np.array(usable, dtype=bool, copy=True, order="C")  # its own, frozen below
        if u.ndim != 2:
            raise ValueError(f"image mask must be (height, width), got shape {u.shape}")
        u.setflags(write=False)
        self.usable = u
        self.source = source  # where it came from (a path, for messages)
        h = hashlib.sha256(f"{u.shape[0]}x{u.shape[1]}|".encode())
        h.update(np.packbits(u).tobytes())
        self.digest = h.hexdigest()[:16]

    def __reduce__(self) -> tuple[type[ImageMask], tuple[np.ndarray, str]]:
        # pickles and deep copies carry the pixels only (not the cached distance transform)
        return (ImageMask, (self.usable, self.source))

    def fill(self, gray: np.ndarray) -> np.ndarray:
        """(height, width) image with the masked pixels set to the median of the usable ones:
        a filter or a descriptor reaching across the mask's edge sees flat ground there, not a
        black stamp or a dark bonnet (a copy; ``gray`` unchanged)."""
        g = np.asarray(gray)
        if g.shape[:2] != self.shape:
            raise ValueError(f"image {g.shape[:2]} and mask {self.shape} differ in size")
        out = g.copy()
        out[~self.usable] = np.median(g[self.usable], axis=0).astype(g.dtype)
        return out

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ImageMask) and other.digest == self.digest

    def __hash__(self) -> int:
        return hash(self.digest)

    def __repr__(self) -> str:
        return f"ImageMask({self.source or 'array'}, {self.masked_share:.1%} masked)"

    def to_report(self) -> dict[str, object]:
        """What report.json says of the mask (docs/formats.md, "Image mask")."""
        return {"file": self.source, "masked_share": round(self.masked_share, 4),
                "digest": self.digest}  # fmt: skip

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.usable.shape[0]), int(self.usable.shape[1]))

    @cached_property
    def masked_share(self) -> float:
        """Share of the image's pixels that are masked (0-1)."""
        return float(1.0 - self.usable.mean())

    @cached_property
    def clearance_px(self) -> np.ndarray:
        """(height, width) float32 distance (px) from each pixel to the nearest masked pixel
        (L2 distance transform; the image border does not count as masked)."""
        if self.usable.all():
            return np.full(self.usable.shape, np.float32(np.inf), np.float32)
        return cv2.distanceTransform(self.usable.astype(np.uint8), cv2.DIST_L2, 5)

    def clearance_at(self, u_raw: np.ndarray, v_raw: np.ndarray) -> np.ndarray:
        """``clearance_px`` (float, px) at raw pixel coordinates (u_raw, v_raw, same shape,
        NaN allowed), nearest pixel; +inf outside the image or where u or v is NaN."""
        u = np.asarray(u_raw, float)
        v = np.asarray(v_raw, float)
        h, w = self.shape
        with np.errstate(invalid="ignore"):
            iu = np.rint(np.nan_to_num(u, nan=-1.0)).astype(np.int64)
            iv = np.rint(np.nan_to_num(v, nan=-1.0)).astype(np.int64)
        inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
        out = np.full(u.shape, np.inf)
        out[inside] = self.clearance_px[iv[inside], iu[inside]]
        return out

    def usable_at(self, px_raw: np.ndarray, margin_px: float | np.ndarray = 0.0) -> np.ndarray:
        """(N,) bool: raw pixels (N, 2) (u right, v down) whose nearest pixel is usable and more
        than ``margin_px`` (scalar or (N,)) from any masked one. Pixels outside the image are
        usable (the image border is the cameras' own business)."""
        px = np.asarray(px_raw, float).reshape(-1, 2)
        d = self.clearance_at(px[:, 0], px[:, 1])
        m = np.broadcast_to(np.asarray(margin_px, float), (len(px),))
        return d > np.maximum(m, 0.0)

    def usable_grid(
        self, u_raw: np.ndarray, v_raw: np.ndarray, margin_px: float = 0.0
    ) -> np.ndarray:
        """Bool array of ``u_raw``'s shape: ``usable_at`` for a grid of raw pixel coordinates
        (u_raw, v_raw, same shape; e.g. a resampling's source pixels)."""
        return self.clearance_at(u_raw, v_raw) > max(float(margin_px), 0.0)

    def eroded(self, margin_px: float) -> np.ndarray:
        """(height, width) bool: usable pixels more than ``margin_px`` from a masked one."""
        return self.clearance_px > max(float(margin_px), 0.0)
