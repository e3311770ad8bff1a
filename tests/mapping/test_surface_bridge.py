"""The local road surface spans a pothole wider than its window (mapping.surface)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.surface import LocalSurface


def _corridor(length_m: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sparse road points (N, 3) of a 1.2 m wide, 10 m long corridor (a nadir camera's) with a
    2 % cross-fall, a 1 cm undulation of 8 m wavelength and 1 mm noise, and a pothole 45 mm deep
    across the whole corridor, ``length_m`` long; (points, true road z (N,), pothole centre)."""
    rng = np.random.default_rng(seed)
    n = 30000
    x, y = rng.uniform(0, 10, n), rng.uniform(0, 1.2, n)
    road = 0.02 * y + 0.01 * np.sin(2 * np.pi * x / 8)
    r = np.hypot((x - 5) / (length_m / 2), (y - 0.6) / 1.5)
    depth = 0.045 * np.clip(1 - r**4, 0, 1)
    return np.column_stack([x, y, road - depth + rng.normal(0, 0.001, n)]), road, r < 0.5


@pytest.mark.parametrize("length_m", [1.5, 2.0])
def test_a_pothole_across_the_corridor_is_bridged(length_m: float) -> None:
    xyz, road, centre = _corridor(length_m)
    err = LocalSurface(MappingConfig(), xyz).height(xyz[:, :2]) - road
    assert abs(np.median(err[centre])) < 0.005  # the floor is 40-45 mm down
    # and the road away from it is as before: the noise only
    assert np.median(np.abs(err[np.abs(xyz[:, 0] - 5) > 2.5])) < 0.001


def test_without_the_coarse_fit_the_surface_follows_the_floor() -> None:
    xyz, road, centre = _corridor(2.0)
    cfg = dataclasses.replace(MappingConfig(), local_fit_bridge_m=0.0)
    err = LocalSurface(cfg, xyz).height(xyz[:, :2]) - road
    assert np.median(err[centre]) < -0.03
