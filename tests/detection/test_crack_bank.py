"""The crack filter's speed-ups give the plain computation's results bit for bit: the filter
bank with shared tile spectra (``crackbank.bank_max``) equals the max over ``cv2.filter2D``,
``exact_median`` equals ``np.median``, and the two segment lengths sharing one darkness image
give the responses each computes alone."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from roadsurf.detection import crackbank
from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackfilter import (
    _line_kernels,
    darkness,
    exact_median,
    line_response,
    thin_dark_components,
)


def _plain_max(img: np.ndarray, kernels: tuple[np.ndarray, ...], border: int) -> np.ndarray:
    c = cv2.filter2D(img, -1, kernels[0], borderType=border)
    for k in kernels[1:]:
        c = np.maximum(c, cv2.filter2D(img, -1, k, borderType=border))
    return c


@pytest.mark.parametrize(
    ("shape", "length", "border"),
    [
        ((240, 320), 32.7, cv2.BORDER_REFLECT),  # the sample drive's long segment: 2 x 2 tiles
        ((97, 413), 21.3, cv2.BORDER_REFLECT),  # odd sizes, one tile row, partial last tile
        ((300, 200), 32.7, cv2.BORDER_REPLICATE),
    ],
)
def test_bank_max_equals_filter2d(shape: tuple[int, int], length: float, border: int) -> None:
    rng = np.random.default_rng(3)
    img = (rng.random(shape) ** 3).astype(np.float32)
    img[40:44, :] += 0.5  # a line, so the directions differ
    kernels = _line_kernels(length)
    assert kernels[0].size >= crackbank.DFT_MIN_TAPS  # the DFT path is exercised
    got = crackbank.bank_max(img, kernels, border)
    want = _plain_max(img, kernels, border)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
    assert crackbank._verified[(*shape, *kernels[0].shape, border)]
    # the replica itself (not the fallback) gave it
    np.testing.assert_array_equal(crackbank._bank_max(img, kernels, border), want)


def test_bank_max_small_kernels_and_fallback(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(4)
    img = rng.random((120, 160), dtype=np.float32)
    small = _line_kernels(10.9)  # 11 x 11: filter2D filters directly; so does bank_max
    np.testing.assert_array_equal(
        crackbank.bank_max(img, small, cv2.BORDER_REFLECT),
        _plain_max(img, small, cv2.BORDER_REFLECT),
    )
    # a build whose DFT path differs: the check fails and plain filter2D is used
    big = _line_kernels(32.7)
    monkeypatch.setattr(crackbank, "_verified", {})
    monkeypatch.setattr(crackbank, "_bank_max", lambda img, k, b: np.zeros_like(img))
    np.testing.assert_array_equal(
        crackbank.bank_max(img, big, cv2.BORDER_REFLECT), _plain_max(img, big, cv2.BORDER_REFLECT)
    )
    with pytest.raises(ValueError, match="no kernel"):
        crackbank.bank_max(img, (), cv2.BORDER_REFLECT)


@pytest.mark.parametrize("n", [16384, 16385, 76800, 307200])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_exact_median_equals_np_median(n: int, dtype: type) -> None:
    rng = np.random.default_rng(n)
    for x in (
        rng.standard_normal(n),
        rng.standard_cauchy(n),  # heavy tails
        rng.random(n) ** 8,  # skewed
        np.round(rng.random(n) * 4),  # ties across the middle
        np.zeros(n),
    ):
        x = x.astype(dtype)
        assert exact_median(x) == float(np.median(x))
    x = rng.random(n).astype(dtype)
    x[7] = np.nan
    assert np.isnan(exact_median(x))  # as np.median
    assert exact_median(np.arange(11.0)) == 5.0  # small: np.median itself


def test_shared_darkness_gives_the_same_responses() -> None:
    rng = np.random.default_rng(5)
    gray = np.clip(rng.normal(120, 18, (240, 320)), 0, 255).astype(np.uint8)
    cv2.line(gray, (30, 200), (290, 60), 70, 2)  # a dark crack-like line
    cfg = CrackConfig()
    m = 0.0018
    dark = darkness(gray, m, cfg)
    for line_m, gsd_m in ((None, None), (cfg.line_long_m, cfg.line_long_gsd_m)):
        alone = line_response(gray, m, cfg, line_m, gsd_m)
        shared = line_response(gray, m, cfg, line_m, gsd_m, dark=dark)
        for a, b in zip(alone, shared, strict=True):
            np.testing.assert_array_equal(a, b)
    # a darkness at another pixel size is not reused
    other = line_response(gray, m, cfg, cfg.line_long_m, 0.008, dark=dark)
    np.testing.assert_array_equal(other[0], line_response(gray, m, cfg, cfg.line_long_m, 0.008)[0])
    lab, keep, widths, _ = thin_dark_components(gray, m, cfg)
    assert keep and np.all(np.isfinite(widths))
