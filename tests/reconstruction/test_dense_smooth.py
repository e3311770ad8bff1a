"""The dense heights' bilateral smoothing filters only the rows holding valid pixels, with the
whole image's result bit for bit (``reconstruction.dense.parallax._smooth``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from roadsurf.reconstruction.dense.parallax import _smooth


def _whole(eta: np.ndarray, valid: np.ndarray, sigma_px: float, range_m: float) -> np.ndarray:
    f = np.where(valid, eta, 1.0).astype(np.float32)
    d = 2 * int(np.ceil(2 * sigma_px)) + 1
    out = cv2.bilateralFilter(f, d, range_m, sigma_px).astype(np.float64)
    return np.where(valid, out, np.nan)


@pytest.mark.parametrize("kind", ["all", "box", "scattered", "box_one_hole", "none"])
def test_the_band_gives_the_whole_images_result(kind: str) -> None:
    rng = np.random.default_rng(3)
    for _ in range(10):
        h, w = (int(v) for v in rng.integers(20, 90, 2))
        eta = rng.normal(0.0, 0.002, (h, w))
        valid = np.zeros((h, w), bool)
        if kind == "all":
            valid[:] = True
        elif kind == "box":
            a, b = sorted(rng.integers(0, h, 2))
            c, e = sorted(rng.integers(0, w, 2))
            valid[a : b + 1, c : e + 1] = True
        elif kind == "scattered":
            valid = rng.random((h, w)) > 0.3
        elif kind == "box_one_hole":  # the band holds no invalid pixel but the one hole
            valid[5 : h - 5] = True
            valid[h // 2, w // 2] = False
        sigma, rng_m = float(rng.uniform(0.5, 3.0)), float(rng.uniform(0.001, 0.01))
        got = _smooth(eta, valid, sigma, rng_m)
        assert np.array_equal(got, _whole(eta, valid, sigma, rng_m), equal_nan=True)
