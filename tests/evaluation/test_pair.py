"""The photo-pair score's distance to the true surface (roadsurf.evaluation.pair): a vertical
difference on a slope of m is 1 / sqrt(1 + m²) of itself away from the surface."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.evaluation.pair import _cos_slope


@pytest.mark.parametrize("m", [0.0, 0.5, 2.0])
def test_cosine_of_a_planar_slope(m: float) -> None:
    gsd = 0.004
    rows, cols = np.mgrid[0:40, 0:50]
    t = m * gsd * (0.6 * cols + 0.8 * rows)  # slope m along a diagonal direction
    c = _cos_slope(t, gsd)
    assert c[5:-5, 5:-5] == pytest.approx(1.0 / np.sqrt(1.0 + m * m), rel=1e-9)


def test_nan_cells_and_their_neighbours_have_no_slope() -> None:
    t = np.zeros((20, 20))
    t[10, 10] = np.nan
    c = _cos_slope(t, 0.004)
    assert np.isnan(c[10, 10]) and np.isnan(c[10, 11]) and np.isnan(c[9, 10])
    assert c[2, 2] == pytest.approx(1.0)
