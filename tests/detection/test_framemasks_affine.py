"""detection.framemasks._enu_from_grid: the affine shortcut of the grid -> ENU transform that
projects many defect cells into the frames agrees with the exact transform per point."""

from __future__ import annotations

import numpy as np

from roadsurf.core.geometry import EnuReference
from roadsurf.detection.framemasks import _enu_from_grid
from roadsurf.detection.mapframe import MapFrame


def test_affine_grid_to_enu_matches_the_exact_transform() -> None:
    # far from the UTM zone's central meridian (the scale varies most there), 60° north
    mf = MapFrame.create(EnuReference(60.0, -77.9, 120.0))
    centre = mf.grid_from_enu(np.array([[3.0, -2.0]]))[0]
    rng = np.random.default_rng(0)
    for extent in (0.3, 5.0, 40.0):  # a pothole, a rut, several defects
        xy = centre + rng.uniform(-extent / 2, extent / 2, (5000, 2))
        exact = mf.enu_from_grid(xy)
        fast = _enu_from_grid(mf, xy)
        assert np.abs(fast - exact).max() < 2e-6  # m
    # without GPS the grid frame is ENU itself
    local = MapFrame.create(None)
    xy = rng.uniform(-5, 5, (200, 2))
    assert np.allclose(_enu_from_grid(local, xy), xy, rtol=0, atol=1e-9)
