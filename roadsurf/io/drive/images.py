"""Frame images: header size, truncation checks, decoding (RGB / grey) and a shared grey cache.

EXIF orientation is ignored everywhere: pixels must stay in the calibrated sensor frame."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from roadsurf.core.errors import FrameReadError
from roadsurf.core.parallel import SharedCache
from roadsurf.io.drive.types import Frame

log = logging.getLogger(__name__)


def image_size_from_header(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG IHDR or JPEG SOF header, or None if not found."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] == b"\xff\xd8":
        i, n = 2, len(data)
        while i + 9 < n:
            if data[i] != 0xFF:
                i += 1
                continue
            m = data[i + 1]
            if m in (0xD8, 0x01) or 0xD0 <= m <= 0xD7 or m == 0xFF:
                i += 1 if m == 0xFF else 2
                continue
            seglen = int.from_bytes(data[i + 2 : i + 4], "big")
            if 0xC0 <= m <= 0xCF and m not in (0xC4, 0xC8, 0xCC):
                h = int.from_bytes(data[i + 5 : i + 7], "big")
                w = int.from_bytes(data[i + 7 : i + 9], "big")
                return w, h
            if m == 0xDA:  # start of scan before any SOF: malformed
                return None
            i += 2 + seglen
    return None


def truncation_reason(data: bytes, name: str) -> str | None:
    """Why the encoded image is incomplete (missing end marker), or None if it looks whole."""
    if not data:
        return "empty file"
    if data[:2] == b"\xff\xd8":
        # Some cameras pad after EOI with zeros or append a few bytes; look near the end only.
        tail = data.rstrip(b"\x00")[-1024:]
        if b"\xff\xd9" not in tail:
            return "truncated JPEG (no end-of-image marker FFD9)"
    elif data[:8] == b"\x89PNG\r\n\x1a\n":
        if b"IEND" not in data[-64:]:
            return "truncated PNG (no IEND chunk)"
    elif Path(name).suffix.lower() in (".jpg", ".jpeg", ".png"):
        return "not a JPEG/PNG file (bad signature bytes)"
    return None


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise FrameReadError(f"{path}: cannot read image ({e}). Check the file.") from e


def _decode(path: Path, flags: int) -> np.ndarray:
    data = _read_bytes(path)
    why = truncation_reason(data, path.name)
    if why is not None:
        raise FrameReadError(f"{path}: {why}. Re-export or remove the frame.")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None or img.size == 0:
        raise FrameReadError(f"{path}: image cannot be decoded. Re-export or remove the frame.")
    if img.dtype != np.uint8:  # 16-bit PNG: scale to 8 bit
        img = (img / 257.0).round().astype(np.uint8) if img.dtype == np.uint16 else None
        if img is None:
            raise FrameReadError(f"{path}: unsupported pixel type; use 8-bit JPEG/PNG.")
    return img


def read_image(frame: Frame) -> np.ndarray:
    """Read a frame as RGB uint8 (H, W, 3); greyscale images are replicated to 3 channels.

    Raises ``FrameReadError`` for unreadable or truncated files.
    """
    # EXIF orientation is ignored: pixels must stay in the calibrated sensor frame.
    img = _decode(Path(frame.path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    return cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2RGB)


def read_gray(frame: Frame) -> np.ndarray:
    """Read a frame as greyscale uint8 (H, W). Raises ``FrameReadError`` when unreadable."""
    img = _decode(Path(frame.path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def check_image(path: Path, full: bool) -> tuple[tuple[int, int] | None, str | None]:
    """Cheap validity check: (width, height) from the header and a failure reason (or None).

    ``full`` also decodes the image (at 1/8 scale for JPEG, which is fast)."""
    try:
        data = path.read_bytes()
    except OSError as e:
        return None, f"cannot read file ({e.strerror or e})"
    why = truncation_reason(data, path.name)
    if why is not None:
        return None, why
    size = image_size_from_header(data)
    if full:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
        if img is None or img.size == 0:
            return size, "image cannot be decoded (corrupt data)"
        if size is None:  # a format without a parsed header: decode fully for the size
            full_img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if full_img is None:
                return None, "image cannot be decoded (corrupt data)"
            size = (int(full_img.shape[1]), int(full_img.shape[0]))
    return size, None


class GrayFrames:
    """Greyscale frames by filename for threads that share them, the ``size`` most recently
    used kept (``roadsurf.core.parallel.SharedCache``). ``get`` gives None for a frame that is not
    in ``frames`` or cannot be read; the latter is logged as ``user: <error>``."""

    def __init__(self, frames: Iterable[Frame], size: int, user: str) -> None:
        self._frames = {f.filename: f for f in frames}
        self._cache: SharedCache[str, np.ndarray | None] = SharedCache(size)
        self._user = user

    def get(self, filename: str) -> np.ndarray | None:
        def load() -> np.ndarray | None:
            f = self._frames.get(filename)
            try:
                return None if f is None else read_gray(f)
            except FrameReadError as e:
                log.warning("%s: %s", self._user, e)
                return None

        return self._cache.get(filename, load)
