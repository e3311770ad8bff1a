"""The dense surface's hole fill (``mapping.rasterise.fill_inward``): holes in the measured
heights continue the cells at their own edge, steps (pothole walls) stay holes."""

from __future__ import annotations

import numpy as np

from roadsurf.mapping.rasterfill import fill_inward

WALL = 6.0  # width of the pothole's wall (cells): 5 mm per cell for 30 mm


def _pothole(n: int = 80, depth: float = 0.03) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, n) residual heights (m): road with 0.5 mm noise around a flat-floored pothole whose
    wall runs from radius 18 to 24 cells; the bool mask of the wall's middle (radius 19-23) and
    each cell's radius."""
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:n, 0:n]
    r = np.hypot(yy - n / 2, xx - n / 2)
    z = -depth * np.clip((24.0 - r) / WALL, 0.0, 1.0) + rng.normal(0, 5e-4, (n, n))
    return z.astype(np.float32), (r > 19.0) & (r < 23.0), r


def test_holes_on_the_road_and_floor_continue_their_edge() -> None:
    z, _, _ = _pothole()
    v = z.copy()
    v[10:14, 10:14] = np.nan  # a hole on the road
    v[38:42, 38:42] = np.nan  # a hole on the pothole's floor
    v[60:80, 0:20] = np.nan  # a hole larger than the fill reaches
    out, near = fill_inward(v, 3.0, 0.003)
    road, floor = out[10:14, 10:14], out[38:42, 38:42]
    assert np.isfinite(road).all() and np.isfinite(floor).all()
    assert np.abs(road).max() < 2e-3  # the road's level, not the pothole's
    assert np.abs(floor + 0.03).max() < 2e-3  # the floor's depth (a 5 cm kernel reads it shallow)
    far = np.zeros_like(near)
    far[63:80, 0:17] = True  # more than 3 cells from any measured cell
    assert np.isnan(out[far]).all() and not near[far].any()
    assert near[10:14, 10:14].all()
    assert np.array_equal(np.isfinite(out) & np.isfinite(v), np.isfinite(v))
    assert np.array_equal(out[np.isfinite(v)], v[np.isfinite(v)])  # measured cells unchanged


def test_a_hole_across_a_pothole_wall_stays_a_hole() -> None:
    """A band of the wall the matching left empty: its edge cells continue their own side flat,
    ring by ring, only from neighbours that agree within the spread (measured here: within
    2.3 cells' relief of the truth); the cells whose neighbours straddle the wall stay holes
    (and are ``near``, so the sparse surface does not fill them either)."""
    z, band, r = _pothole()
    band[:, :30] = False  # part of the wall is missing
    v = z.copy()
    v[band] = np.nan
    spread = 0.003
    out, near = fill_inward(v, 3.0, spread)
    assert near[band].all()
    got = band & np.isfinite(out)
    per_cell = 0.03 / WALL
    assert np.abs(out[got] - z[got]).max() < spread + 2 * per_cell
    mid = band & (r > 20.5) & (r < 21.5)
    assert np.isnan(out[mid]).mean() > 0.8  # measured 0.87
    # with a spread above the wall's depth every cell is filled, between rim and floor
    out2, _ = fill_inward(v, 3.0, 0.05)
    assert np.isfinite(out2[band]).all()
    assert (out2[band] < -0.002).mean() > 0.8 and (out2[band] > -0.028).mean() > 0.8


def test_nothing_to_fill() -> None:
    z, _, _ = _pothole(20)
    out, near = fill_inward(z, 3.0, 0.003)
    assert np.array_equal(out, z) and near.all()
    empty = np.full((5, 5), np.nan, np.float32)
    out, near = fill_inward(empty, 3.0, 0.003)
    assert np.isnan(out).all() and not near.any()
    out, near = fill_inward(z, 0.0, 0.003)
    assert np.array_equal(out, z)
