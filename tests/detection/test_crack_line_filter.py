"""The oriented line filter of the crack detector (detection.crackfilter.thin_dark_components) on a
real gravel photo (skimage.data.gravel): its stone gaps answer a point-wise black top-hat as
strongly as a clearly visible crack does; averaging along 4 cm segments separates them."""

import cv2
import numpy as np
import pytest
import skimage.data

from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackfilter import thin_dark_components

M_PER_PX = 0.0015  # ground size of a pixel (m), as on a survey camera 1-2 mm/px


def _gravel() -> np.ndarray:
    """The gravel photo at half size, tiled to 512 x 512: stones ~1 cm at 1.5 mm/px."""
    g = skimage.data.gravel().astype(np.float32)
    g = cv2.resize(g, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    return np.tile(g, (2, 2))


def _with_crack(g: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A curved crack (random walk in direction, ~0.5 m): 60 % darker at its centre line,
    fading over 3 px to each side, like a rendered groove. Returns (image, centre line mask)."""
    rng = np.random.default_rng(seed)
    ang = 0.6 + np.cumsum(rng.normal(0, 0.15, 40))
    pts = np.vstack([[120.0, 100.0], 120 + np.cumsum(np.c_[np.cos(ang), np.sin(ang)] * 8, 0)])
    line = np.zeros(g.shape, np.uint8)
    cv2.polylines(line, [np.round(pts * 16).astype(np.int32)], False, 1, 1, cv2.LINE_8, 4)
    d = cv2.distanceTransform(1 - line, cv2.DIST_L2, 5)
    out = g * (1 - 0.6 * np.clip(1 - d / 3.0, 0, 1))
    return out, line


def _u8(g: np.ndarray) -> np.ndarray:
    return np.clip(np.round(g), 0, 255).astype(np.uint8)


def _found(g: np.ndarray, line: np.ndarray) -> tuple[int, float, float]:
    """(kept components, share of their pixels on the crack, share of the crack covered)."""
    lab, keep, *_ = thin_dark_components(g, M_PER_PX, CrackConfig())
    det = np.isin(lab, keep)
    near = cv2.dilate(line, np.ones((7, 7), np.uint8)) > 0
    on = float(near[det].mean()) if det.any() else 0.0
    cover = cv2.dilate(det.astype(np.uint8), np.ones((7, 7), np.uint8))[line > 0] > 0
    return len(keep), on, float(cover.mean())


def test_crack_on_gravel_photo_is_found():
    g, line = _with_crack(_gravel())
    n, on, cover = _found(_u8(g), line)
    assert n >= 1 and on > 0.95 and cover > 0.5, (n, on, cover)


@pytest.mark.parametrize("contrast", [0.4, 0.2])
def test_crack_on_low_contrast_image_is_found(contrast):
    """The whole image (texture and crack) at a fraction of its contrast, as under flat light
    or a dark exposure: the thresholds are relative to the image, the crack is still found."""
    g, line = _with_crack(_gravel())
    low = np.median(g) + contrast * (g - np.median(g))
    n, on, cover = _found(_u8(low), line)
    assert n >= 1 and on > 0.95 and cover > 0.5, (contrast, n, on, cover)


@pytest.mark.parametrize("m_per_px", [0.001, 0.0015, 0.002])
def test_pure_gravel_texture_yields_nothing(m_per_px):
    for g in (skimage.data.gravel(), _u8(_gravel())):
        lab, keep, *_ = thin_dark_components(g, m_per_px, CrackConfig())
        assert keep == []


def test_straight_edges_of_wide_regions_yield_no_line():
    """A lane marking (bright band) and a shadow (dark half) on a noisy road: their straight
    high-contrast borders are no thin dark structure (the top-hat ignores a step)."""
    rng = np.random.default_rng(3)
    g = 110 + rng.normal(0, 8, (480, 640))
    g[:, 200:260] += 100  # lane marking, 9 cm at 1.5 mm/px
    g[:, 420:] *= 0.5  # shadow border
    lab, keep, *_ = thin_dark_components(_u8(g), M_PER_PX, CrackConfig())
    assert keep == []


def test_long_segment_finds_a_thin_straight_crack_the_short_one_misses():
    """A thin (2 px) nearly straight crack on the gravel photo: along 4 cm it answers no more
    than the stones' gaps; along 12 cm (``line_long_m``) it stands out, and nothing else
    does (the pure texture tests above run with the long segment on)."""
    import dataclasses

    rng = np.random.default_rng(0)
    ang = 0.6 + np.cumsum(rng.normal(0, 0.04, 60))
    pts = np.vstack([[60.0, 40.0], 60 + np.cumsum(np.c_[np.cos(ang), np.sin(ang)] * 8, 0)])
    line = np.zeros((512, 512), np.uint8)
    cv2.polylines(line, [np.round(pts * 16).astype(np.int32)], False, 1, 1, cv2.LINE_8, 4)
    d = cv2.distanceTransform(1 - line, cv2.DIST_L2, 5)
    g = _u8(_gravel() * (1 - 0.6 * np.clip(1 - d / 2.0, 0, 1)))
    short_only = dataclasses.replace(CrackConfig(), line_long_m=0.0)
    lab, keep, *_ = thin_dark_components(g, M_PER_PX, short_only)
    assert keep == []
    n, on, cover = _found(g, line)
    assert n >= 1 and on > 0.95 and cover > 0.3, (n, on, cover)
