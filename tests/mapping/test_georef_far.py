"""Georeferencing far from the GPS log's first fix, high above the ellipsoid (a fault battery
found La Paz at 3,640 m with the log started 1 km from the frames placing the map 0.4-0.6 m
off): the ENU origin sits in the drive, raster cells are placed at the road's height, and
exported heights are ellipsoidal through ECEF."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.core.geometry import (
    EnuReference,
    ExportFrame,
    enu_from_lla,
    lla_from_enu,
    lla_from_utm,
    utm_from_lla,
)
from roadsurf.io.drive import GpsTrack
from roadsurf.io.formats import GridSpec
from roadsurf.mapping.pose_gps import enu_reference
from roadsurf.mapping.raster import GridToEnu

REF = EnuReference(-16.5, -68.15, 3640.0)


@pytest.mark.parametrize("north_m", [1000.0, 5000.0])
def test_grid_cells_land_on_the_road_at_altitude(north_m: float) -> None:
    ef = ExportFrame.for_reference(REF)
    e0, n0 = utm_from_lla(np.array([REF.lat_deg]), np.array([REF.lon_deg]), ef.epsg)[0]
    grid = GridSpec(ef.crs, e0 - 1.0, n0 + north_m + 1.0, 0.005, 400, 400)
    e, n = GridToEnu(REF, ef.epsg).pixel_enu(grid, slice(200, 201), slice(200, 201))
    # the cell's centre on the road (the reference's altitude) in ENU: what the map placed there
    x, y = grid.x0_m + 200.5 * grid.gsd_m, grid.y0_m - 200.5 * grid.gsd_m
    lat, lon = lla_from_utm(np.array([x]), np.array([y]), ef.epsg)[0]
    want = enu_from_lla(lat, lon, REF.alt_m, REF)[0]
    assert np.hypot(e[0, 0] - want[0], n[0, 0] - want[1]) < 0.005  # was 0.57 m at 1 km
    # and exported back: the same easting, northing and ellipsoidal height
    back = ef.utm_from_enu(want[None])[0]
    assert back[:2] == pytest.approx([x, y], abs=0.002)
    assert back[2] == pytest.approx(REF.alt_m, abs=0.002)  # ENU up + alt: 8 cm low at 1 km


def test_exported_height_is_ellipsoidal_far_from_the_reference() -> None:
    ef = ExportFrame.for_reference(REF)
    enu = np.array([[3000.0, -2000.0, -0.7], [0.0, 0.0, 1.5]])
    h = ef.utm_from_enu(enu)[:, 2]
    assert h == pytest.approx(lla_from_enu(enu, REF)[:, 2], abs=1e-6)
    assert h[1] == pytest.approx(REF.alt_m + 1.5, abs=1e-6)
    assert abs(h[0] - (REF.alt_m - 0.7)) > 0.5  # 3.6 km out: the tangent plane is 1 m up


def test_enu_reference_is_the_fix_nearest_the_middle_frame() -> None:
    # a logger started at the depot: 600 s of fixes 5 km south before the drive's frames
    ts = np.r_[np.arange(-600.0, 0.0), np.arange(0.0, 10.0, 0.2)]
    lat = np.r_[np.linspace(REF.lat_deg - 0.045, REF.lat_deg, 600), np.full(50, REF.lat_deg)]
    lon = np.full(len(ts), REF.lon_deg)
    alt = np.full(len(ts), REF.alt_m)
    alt[-50:-20] = np.nan  # the nearest fix without an altitude takes its neighbour's
    g = GpsTrack(ts, lat, lon + np.r_[np.zeros(600), np.linspace(0, 1e-3, 50)], alt,
                 np.full(len(ts), 0.8))  # fmt: skip
    frames_t = np.linspace(1.0, 9.0, 41)
    ref = enu_reference(g, frames_t)
    i = int(np.argmin(np.abs(ts - 5.0)))
    assert (ref.lat_deg, ref.lon_deg) == (g.lat_deg[i], g.lon_deg[i])
    assert ref.alt_m == pytest.approx(REF.alt_m)


@pytest.mark.parametrize("north_m", [0.0, 1000.0, 5000.0])
def test_dense_cloud_heights_are_the_exports_ellipsoidal_heights(north_m: float) -> None:
    """cloud.ply's dense points (grid x, y; ENU up + the tile's lift) and the sparse ones
    (ExportFrame.utm_from_enu) carry the same ellipsoidal height: the lift is the tangent
    plane's rise, d² / 2R (7.8 cm at 1 km, 2 m at 5 km)."""
    ef = ExportFrame.for_reference(REF)
    g2e = GridToEnu(REF, ef.epsg)
    e0, n0 = utm_from_lla(np.array([REF.lat_deg]), np.array([REF.lon_deg]), ef.epsg)[0]
    grid = GridSpec(ef.crs, e0 - 2.0, n0 + north_m + 2.5, 0.005, 800, 1000)
    rng = np.random.default_rng(3)
    rows, cols = rng.integers(0, 1000, 50), rng.integers(0, 800, 50)
    e, n = g2e.pixel_enu(grid, slice(0, 1000), slice(0, 800))
    x = grid.x0_m + (cols + 0.5) * grid.gsd_m
    y = grid.y0_m - (rows + 0.5) * grid.gsd_m
    up = rng.uniform(-0.05, 0.02, 50) - (north_m**2) / (2 * 6.371e6)  # the road, ENU
    h = up + REF.alt_m + g2e.height_lift(grid, x, y)
    want = ef.utm_from_enu(np.column_stack([e[rows, cols], n[rows, cols], up]))
    assert want[:, :2] == pytest.approx(np.column_stack([x, y]), abs=0.003)
    assert h == pytest.approx(want[:, 2], abs=0.001)
