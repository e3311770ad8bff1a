"""The dense surface's hole fill (``mapping.rasterfill.fill_inward``): holes in the measured
heights continue the cells at their own edge; across a step (a pothole wall) they ramp."""

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


def test_a_hole_across_a_pothole_wall_is_a_ramp_from_rim_to_floor() -> None:
    """A band of the wall the matching left empty: the flat continuation of each side would
    meet in the band's middle (a step there: the pothole's outline half a band inside its
    rim); it is filled by harmonic interpolation between rim and floor instead, which on this
    straight wall is the wall itself."""
    z, band, r = _pothole()
    band[:, :30] = False  # part of the wall is missing
    v = z.copy()
    v[band] = np.nan
    out, near = fill_inward(v, 3.0, 0.003)
    assert near[band].all() and np.isfinite(out[band]).all()
    err = out[band] - z[band]
    assert np.abs(err).max() < 4e-3 and np.abs(err).mean() < 1.5e-3  # wall 5 mm per cell
    assert out[band].max() <= np.nanmax(v) and out[band].min() >= np.nanmin(v)
    # the outline at T_d = 5 mm: at the truth's radius (23.0 cells), not the band's middle
    td = band & (r > 22.0) & (r < 23.0)
    assert (out[td] < -0.002).mean() > 0.9
    # a hole on one level keeps that level (the ring fill), the step's fill is local
    assert np.array_equal(out[np.isfinite(v)], v[np.isfinite(v)])


def test_harmonic_fill_of_a_gap_between_two_levels_is_linear() -> None:
    v = np.full((5, 12), np.nan, np.float32)
    v[:, :2] = 0.0
    v[:, 10:] = -0.08
    out, _ = fill_inward(v, 5.0, 0.003)
    ramp = np.interp(np.arange(2, 10), [1, 10], [0.0, -0.08])
    assert np.allclose(out[:, 2:10], ramp[None, :], atol=1e-4)


def test_nothing_to_fill() -> None:
    z, _, _ = _pothole(20)
    out, near = fill_inward(z, 3.0, 0.003)
    assert np.array_equal(out, z) and near.all()
    empty = np.full((5, 5), np.nan, np.float32)
    out, near = fill_inward(empty, 3.0, 0.003)
    assert np.isnan(out).all() and not near.any()
    out, near = fill_inward(z, 0.0, 0.003)
    assert np.array_equal(out, z)


def test_a_hole_beyond_the_ramp_cap_keeps_the_ring_fill(monkeypatch) -> None:
    """A fragmented tile's web of holes is not one huge sparse solve: beyond MAX_RAMP_CELLS a
    component keeps the ring fill, its step cells empty."""
    import roadsurf.mapping.rasterfill as rf

    z, band, r = _pothole()
    band[:, :30] = False
    v = z.copy()
    v[band] = np.nan
    monkeypatch.setattr(rf, "MAX_RAMP_CELLS", 10)
    out, near = fill_inward(v, 3.0, 0.003)
    mid = band & (r > 20.5) & (r < 21.5)
    assert np.isnan(out[mid]).mean() > 0.5
