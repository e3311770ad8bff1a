"""Augmentation of defect images against class imbalance (dissertation §5.3.2).

Real drives are > 99% non-defect. Each defect image yields copies with the defect translated to
the left, right, top, bottom and centre of the image, rescaled, rotated by 90/180/270 degrees and
flipped. Images are square greyscale uint8 thumbnails; ``bbox`` is the defect's box
(x0, y0, x1, y1) in thumbnail pixels (None when unknown: translations then use the image centre).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:  # torch is imported where it is used: the pipeline imports this module
    import torch  # (via dataset -> guided) and a fused run imports torch only to screen

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


# ---------------------------------------------------------------- photometric (on-line, torch)
def photometric(x: torch.Tensor, gen: torch.Generator, strength: float = 1.0) -> torch.Tensor:
    """Random camera/lighting changes of a grey batch (N, 1, S, S), 0-255 -> float 0-255.

    Unseen drives differ in exposure, gamma/tone curve, contrast, sensor noise, blur and smooth
    illumination gradients (sun, clouds, vignetting), and may be 8-bit greyscale from a dark
    exposure (coarse grey levels). Each image gets its own random draw, so the CNN learns the
    defect's shape and shading rather than one camera's rendering. ``strength`` scales every
    range (0 = identity). Geometric changes are elsewhere (``augment_image``, dihedral turns).
    """
    import torch

    if strength <= 0:
        return x.float()
    n, _, s, _ = x.shape
    x = x.float() / 255.0

    def u(lo: float, hi: float) -> torch.Tensor:  # one value per image, shape (N, 1, 1, 1)
        return lo + (hi - lo) * torch.rand((n, 1, 1, 1), generator=gen)

    k = float(strength)
    # smooth illumination: a random linear ramp (cloud edge, vignetting, sun falloff)
    ang = u(0.0, 2 * math.pi)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, s), torch.linspace(-1, 1, s), indexing="ij")
    ramp = torch.cos(ang) * xx + torch.sin(ang) * yy
    x = x * (1.0 + u(-0.25 * k, 0.25 * k) * ramp)
    # tone curve (gamma) and exposure gain, clipped like a real sensor
    x = x.clamp(0, 1) ** torch.exp(u(-0.5 * k, 0.5 * k))
    x = (x * torch.exp(u(-0.6 * k, 0.4 * k))).clamp(0, 1)
    # contrast about the image mean (flat ambient light vs hard sun)
    m = x.mean(dim=(2, 3), keepdim=True)
    x = (m + (x - m) * torch.exp(u(-0.5 * k, 0.3 * k))).clamp(0, 1)
    # blur (defocus, motion) for about a third of the images: a 3x3 binomial kernel, mixed in
    blur_w = (torch.rand((n, 1, 1, 1), generator=gen) < 0.35).float() * u(0.0, 1.0)
    ker = torch.tensor([1.0, 2.0, 1.0])
    ker = (ker[:, None] * ker[None, :] / 16.0).view(1, 1, 3, 3)
    xb = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (1, 1, 1, 1), "replicate"), ker)
    x = x + blur_w * (xb - x)
    # sensor noise
    x = x + torch.randn(x.shape, generator=gen) * u(0.0, 0.02 * k)
    # coarse grey levels (dark 8-bit exposure brightened later) for about a quarter of them
    levels = torch.where(
        torch.rand((n, 1, 1, 1), generator=gen) < 0.25,
        u(24.0, 96.0),
        torch.full((n, 1, 1, 1), 255.0),
    )
    x = torch.round(x.clamp(0, 1) * levels) / levels
    return x * 255.0
