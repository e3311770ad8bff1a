"""Augmentation of defect images against class imbalance (dissertation §5.3.2).

Real drives are > 99% non-defect. Each defect image yields copies with the defect translated to
the left, right, top, bottom and centre of the image, rescaled, rotated by 90/180/270 degrees and
flipped. Images are square greyscale uint8 thumbnails; ``bbox`` is the defect's box
(x0, y0, x1, y1) in thumbnail pixels (None when unknown: translations then use the image centre).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

Bbox = tuple[float, float, float, float]
Transform = Callable[[np.ndarray, Bbox | None], np.ndarray]


def _shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    s = img.shape[0]
    m = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], dtype=np.float64)
    # mirrored borders keep road texture at the edges instead of black bars
    return cv2.warpAffine(img, m, (s, s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)


def translate_to(img: np.ndarray, bbox: Bbox | None, where: str) -> np.ndarray:
    """Move the defect centre to ``where`` in {left, right, up, down, centre}."""
    s = img.shape[0]
    cx, cy = ((bbox[0] + bbox[2]) / 2, (bbox[1] + bbox[3]) / 2) if bbox else (s / 2, s / 2)
    targets = {
        "left": (0.25 * s, s / 2),
        "right": (0.75 * s, s / 2),
        "up": (s / 2, 0.25 * s),
        "down": (s / 2, 0.75 * s),
        "centre": (s / 2, s / 2),
    }
    tx, ty = targets[where]
    return _shift(img, tx - cx, ty - cy)


def rescale(img: np.ndarray, bbox: Bbox | None, factor: float) -> np.ndarray:
    """Zoom by ``factor`` about the defect centre (>1 enlarges), keeping the image size."""
    s = img.shape[0]
    cx, cy = ((bbox[0] + bbox[2]) / 2, (bbox[1] + bbox[3]) / 2) if bbox else (s / 2, s / 2)
    m = cv2.getRotationMatrix2D((cx, cy), 0.0, factor)
    return cv2.warpAffine(
        img,
        m,
        (s, s),
        flags=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT_101,
    )


def rotate(img: np.ndarray, quarter_turns: int) -> np.ndarray:
    """Rotate by 90° * quarter_turns (counter-clockwise)."""
    return np.ascontiguousarray(np.rot90(img, quarter_turns))


def flip(img: np.ndarray, axis: str) -> np.ndarray:
    """Mirror left-right (``h``) or top-bottom (``v``)."""
    return np.ascontiguousarray(img[:, ::-1] if axis == "h" else img[::-1, :])


def transforms(rescale_range: tuple[float, float] = (0.8, 1.25)) -> list[tuple[str, Transform]]:
    """All augmentations in a fixed order: (name, fn(img, bbox) -> img)."""
    lo, hi = rescale_range
    out: list[tuple[str, Transform]] = []
    for where in ("left", "right", "up", "down", "centre"):
        out.append((f"translate_{where}", lambda im, bb, w=where: translate_to(im, bb, w)))
    out.append(("rot90", lambda im, bb: rotate(im, 1)))
    out.append(("rot180", lambda im, bb: rotate(im, 2)))
    out.append(("rot270", lambda im, bb: rotate(im, 3)))
    out.append(("flip_h", lambda im, bb: flip(im, "h")))
    out.append(("flip_v", lambda im, bb: flip(im, "v")))
    out.append((f"scale_{hi:g}", lambda im, bb: rescale(im, bb, hi)))
    out.append((f"scale_{lo:g}", lambda im, bb: rescale(im, bb, lo)))
    return out


def copies_needed(n_defect: int, n_non_defect: int, target_ratio: float, max_copies: int) -> int:
    """Augmented copies per defect image so that defect ≈ target_ratio × non-defect."""
    if n_defect == 0:
        return 0
    want = target_ratio * n_non_defect - n_defect
    return int(min(max_copies, max(0, np.ceil(want / n_defect))))


def augment_image(
    img: np.ndarray,
    bbox: Bbox | None,
    n_copies: int,
    rng: np.random.Generator,
    rescale_range: tuple[float, float] = (0.8, 1.25),
) -> list[tuple[str, np.ndarray]]:
    """Up to ``n_copies`` distinct augmentations of one image, chosen at random (seeded)."""
    if img.ndim != 2 or img.shape[0] != img.shape[1]:
        raise ValueError(f"augment_image expects a square greyscale image, got {img.shape}")
    pool = transforms(rescale_range)
    pick = rng.permutation(len(pool))[: min(n_copies, len(pool))]
    # combine a translation with a rotation/flip once the single transforms are used up
    out = [(pool[i][0], pool[i][1](img, bbox)) for i in sorted(pick)]
    extra = n_copies - len(out)
    for _ in range(max(0, extra)):
        a, b = rng.choice(5), 5 + rng.choice(len(pool) - 5)
        name = f"{pool[a][0]}+{pool[b][0]}"
        out.append((name, pool[b][1](pool[a][1](img, bbox), None)))
    return out
