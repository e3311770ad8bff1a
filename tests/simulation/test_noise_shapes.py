"""Procedural noise and shapes used by the simulator world."""

from __future__ import annotations

import numpy as np

from roadsurf.simulation.noise import fractal_noise, value_noise
from roadsurf.simulation.shapes import Blob, Polyline, Rect


def test_value_noise_unit_std_and_position_only() -> None:
    x, y = np.meshgrid(np.arange(0, 40, 0.05), np.arange(0, 40, 0.05))
    a = value_noise(x, y, 0.5, 7)
    assert abs(float(a.std()) - 1.0) < 0.05 and abs(float(a.mean())) < 0.05
    # The field depends on the position only, not on which window asks for it.
    sub = value_noise(x[100:140, 200:260], y[100:140, 200:260], 0.5, 7)
    np.testing.assert_allclose(sub, a[100:140, 200:260], atol=1e-5)
    assert not np.allclose(value_noise(x[:5, :5], y[:5, :5], 0.5, 8), a[:5, :5])
    f = fractal_noise(x, y, (0.5, 2.0), (1.0, 0.5), 3)
    assert abs(float(f.std()) - 1.0) < 0.1


def test_shapes_masks_and_distances() -> None:
    b = Blob(1.0, 2.0, 0.3, (0.1, 0.05), (0.3, 1.0))
    ring = b.outline(64)
    rho, _ = b.rho_and_r(ring[:, 0], ring[:, 1])
    np.testing.assert_allclose(rho, 1.0, atol=1e-9)
    assert b.soft_mask(np.array([1.0]), np.array([2.0]), 0.01)[0] == 1.0
    r = Rect(0.0, 0.0, np.pi / 2, 2.0, 0.2)  # long axis north
    m = r.soft_mask(np.array([0.0, 0.0, 0.5]), np.array([0.9, 1.2, 0.0]), 0.01)
    np.testing.assert_allclose(m, [1.0, 0.0, 0.0])
    line = Polyline(((0.0, 0.0), (1.0, 0.0), (1.0, 1.0)), 0.01)
    d, along = line.distance(np.array([0.5, 1.2]), np.array([0.1, 0.5]))
    np.testing.assert_allclose(d, [0.1, 0.2])
    np.testing.assert_allclose(along, [0.5, 1.5])
