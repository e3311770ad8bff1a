"""The photo-pair score's distance to the true surface (roadsurf.evaluation.pair): a point a
vertical d above a plane of slope m is d / sqrt(1 + m²) from it; on flat road the distance is
the vertical difference; nothing under the point, no distance."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.evaluation.pair import SURFACE_STEP_M, _surface_distance


@pytest.mark.parametrize("m", [0.0, 0.5, 2.0])
def test_distance_to_a_sloped_plane(m: float) -> None:
    rng = np.random.default_rng(1)
    e, n = rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50)
    d = rng.uniform(-0.006, 0.006, 50)

    def plane(e: np.ndarray, n: np.ndarray) -> np.ndarray:
        return m * (0.6 * e + 0.8 * n)

    got = _surface_distance(e, n, plane(e, n) + d, plane)
    want = np.abs(d) / np.sqrt(1 + m * m)
    # the 0.5 mm search lattice: the nearest lattice point is at most half a diagonal away
    assert got == pytest.approx(
        want, abs=0.5 * SURFACE_STEP_M * np.sqrt(2) * m / np.sqrt(1 + m * m) + 1e-12
    )
    assert np.all(got <= np.abs(d) + 1e-12)


def test_no_surface_under_the_point_gives_no_distance() -> None:
    def half(e: np.ndarray, n: np.ndarray) -> np.ndarray:
        return np.where(e > 0, 0.0, np.nan)

    got = _surface_distance(np.array([0.5, -0.5]), np.zeros(2), np.array([0.003, 0.003]), half)
    assert got[0] == pytest.approx(0.003) and np.isnan(got[1])
