import json

import numpy as np
import pytest
import rasterio
from plyfile import PlyData

from roadsurf.core.atomic import write_json_atomic
from roadsurf.io.formats import (
    GridSpec,
    feature,
    polygon_geometry,
    read_csv,
    read_geojson,
    read_geotiff,
    read_ply,
    write_csv,
    write_geojson,
    write_geotiff,
    write_ply,
)


def test_ply_round_trip_is_binary_with_contract_types(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 1, (100, 3)) + [630000.0, 4833000.0, 80.0]
    rgb = rng.integers(0, 256, (100, 3)).astype(np.uint8)
    res = rng.normal(0, 0.01, 100)
    p = write_ply(tmp_path / "cloud.ply", xyz, rgb, {"residual_m": res})
    ply = PlyData.read(str(p))
    assert not ply.text
    props = {pr.name: pr.val_dtype for pr in ply["vertex"].properties}
    assert props["x"] == "f8" and props["red"] == "u1" and props["residual_m"] == "f4"
    back = read_ply(p)
    np.testing.assert_array_equal(back["xyz"], xyz)  # doubles keep UTM precision
    np.testing.assert_array_equal(back["rgb"], rgb)
    np.testing.assert_allclose(back["residual_m"], res, rtol=1e-6)


def test_geotiff_round_trip_float_and_rgb(tmp_path):
    grid = GridSpec("EPSG:32617", 630000.0, 4833010.0, 0.005, 600, 300)
    surf = np.full((300, 600), np.nan, np.float32)
    surf[100:120, 200:260] = -0.03
    write_geotiff(tmp_path / "surface.tif", surf, grid, nodata=float("nan"))
    data, g2, nodata = read_geotiff(tmp_path / "surface.tif")
    assert g2 == grid and np.isnan(nodata)
    np.testing.assert_array_equal(np.isnan(data), np.isnan(surf))
    with rasterio.open(tmp_path / "surface.tif") as src:
        assert src.crs.to_epsg() == 32617 and src.dtypes[0] == "float32"
        # Pixel centre of (row 100, col 200) maps to the expected easting/northing.
        x, y = src.xy(100, 200)
    assert np.allclose(grid.xy_from_rowcol(100, 200), [[x, y]])
    np.testing.assert_allclose(grid.rowcol_from_xy(np.array([[x, y]])), [[100, 200]])
    rgb = np.zeros((300, 600, 3), np.uint8)
    rgb[..., 1] = 200
    write_geotiff(tmp_path / "mosaic.tif", rgb, grid)
    back, _, _ = read_geotiff(tmp_path / "mosaic.tif")
    np.testing.assert_array_equal(back, rgb)


def test_geotiff_shape_mismatch_is_an_error(tmp_path):
    grid = GridSpec("EPSG:32617", 0.0, 0.0, 1.0, 10, 10)
    with pytest.raises(ValueError, match="grid is"):
        write_geotiff(tmp_path / "x.tif", np.zeros((5, 10), np.float32), grid)


def test_geojson_polygons_closed_ccw_and_validated(tmp_path):
    ring = np.array([[-79.38, 43.65], [-79.38, 43.6501], [-79.3799, 43.6501]])  # clockwise
    f = feature(
        polygon_geometry(ring), {"id": 1, "max_depth_m": np.float32(0.03), "x": float("nan")}
    )
    write_geojson(tmp_path / "d.geojson", [f])
    fc = read_geojson(tmp_path / "d.geojson")
    coords = fc["features"][0]["geometry"]["coordinates"][0]
    assert coords[0] == coords[-1] and len(coords) == 4
    xs, ys = np.array(coords).T
    assert 0.5 * np.sum(xs[:-1] * ys[1:] - xs[1:] * ys[:-1]) > 0  # counter-clockwise
    assert fc["features"][0]["properties"]["x"] is None  # NaN is not valid JSON
    bad = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [630000.0, 4833000.0]},
                "properties": {},
            }
        ],
    }
    write_json_atomic(tmp_path / "bad.geojson", bad)
    with pytest.raises(ValueError, match="lon/lat"):
        read_geojson(tmp_path / "bad.geojson")


def test_csv_round_trip(tmp_path):
    write_csv(tmp_path / "a.csv", ["filename", "p"], [["f1.jpg", 0.25], ["f2.jpg", float("nan")]])
    rows = read_csv(tmp_path / "a.csv")
    assert rows == [{"filename": "f1.jpg", "p": "0.25"}, {"filename": "f2.jpg", "p": ""}]


def test_atomic_write_leaves_no_temp_on_failure(tmp_path):
    from roadsurf.core.atomic import atomic_path

    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "x.json") as tmp:
            tmp.write_text("partial")
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []
    write_json_atomic(tmp_path / "y.json", {"a": np.float64(1.5)})
    assert json.loads((tmp_path / "y.json").read_text()) == {"a": 1.5}


def test_geotiff_blocks_sparse_round_trip(tmp_path):
    from roadsurf.io.formats import write_geotiff_blocks

    # A long thin diagonal corridor in a large box: only the written blocks are stored.
    grid = GridSpec("EPSG:32617", 630000.0, 4833000.0, 0.005, 4096, 4096)
    blocks = [
        (i * 256, i * 256, np.full((256, 256), -0.01 * (i + 1), np.float32)) for i in range(16)
    ]
    p = write_geotiff_blocks(tmp_path / "s.tif", grid, blocks, nodata=float("nan"))
    data, g2, nodata = read_geotiff(p)
    assert g2 == grid and np.isnan(nodata)
    for i in range(16):
        np.testing.assert_array_equal(
            data[i * 256 : (i + 1) * 256, i * 256 : (i + 1) * 256], np.float32(-0.01 * (i + 1))
        )
    assert np.isnan(data[0, 4000]) and np.isnan(data[4000, 0])
    # Sparse: 16 of 256 tiles written, so the file is far smaller than a dense float32 raster.
    assert p.stat().st_size < 0.1 * 4096 * 4096 * 4


def test_atomic_outputs_are_not_private(tmp_path):
    import os
    import stat

    p = write_json_atomic(tmp_path / "r.json", {"a": 1})
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~mask


def test_geotiff_local_frame_round_trip(tmp_path):
    from roadsurf.io.formats import LOCAL_CRS

    # A run without GPS: the raster has no CRS, and reads back as the local frame.
    grid = GridSpec(LOCAL_CRS, -5.0, 20.0, 0.01, 40, 30)
    write_geotiff(tmp_path / "s.tif", np.zeros((30, 40), np.float32), grid, nodata=float("nan"))
    with rasterio.open(tmp_path / "s.tif") as src:
        assert src.crs is None
    _, g2, _ = read_geotiff(tmp_path / "s.tif")
    assert g2 == grid


def test_geojson_cut_at_the_antimeridian(tmp_path):
    """RFC 7946 §3.1.9: a defect and a trajectory on a road across ±180° (Taveuni, Fiji) are
    written as parts that do not cross; their area and path are kept, the rest is untouched."""
    from pyproj import Geod
    from shapely.geometry import shape

    d = 1e-5  # about 1.1 m
    ring = np.array(
        [[180 - d, -16.8], [-180 + d, -16.8], [-180 + d, -16.8 + d], [180 - d, -16.8 + d]]
    )
    line = [[180 - 2 * d, -16.8], [180 - d / 2, -16.8 + d], [-180 + d, -16.8 + 3 * d]]
    home = polygon_geometry(np.array([[-79.38, 43.65], [-79.3799, 43.65], [-79.3799, 43.6501]]))
    feats = [
        feature(polygon_geometry(ring), {"id": 1}),
        feature({"type": "LineString", "coordinates": line}, {"kind": "trajectory"}),
        feature(home, {"id": 2}),
    ]
    write_geojson(tmp_path / "fiji.geojson", feats)
    fc = read_geojson(tmp_path / "fiji.geojson")
    poly, path, kept = (f["geometry"] for f in fc["features"])
    assert poly["type"] == "MultiPolygon" and len(poly["coordinates"]) == 2
    geod = Geod(ellps="WGS84")
    parts = [shape({"type": "Polygon", "coordinates": p}) for p in poly["coordinates"]]
    areas = [geod.geometry_area_perimeter(p)[0] for p in parts]
    assert all(a > 0 for a in areas)  # counter-clockwise, as RFC 7946 asks
    whole = 2 * d * 111_320 * np.cos(np.radians(16.8)) * d * 110_600  # about 1.2 m²
    assert abs(sum(areas) / whole - 1) < 0.02, (areas, whole)
    for p in parts:
        lon = np.asarray(p.exterior.coords)[:, 0]
        assert p.is_valid and np.ptp(lon) < 1e-3  # each part stays on its side
    assert path["type"] == "MultiLineString" and len(path["coordinates"]) == 2
    a_end, b_start = path["coordinates"][0][-1], path["coordinates"][1][0]
    assert abs(a_end[0]) == 180 and a_end[0] == -b_start[0] and a_end[1] == b_start[1]
    assert -16.8 + d < a_end[1] < -16.8 + 3 * d
    assert kept == home  # a geometry that does not cross is written as it is


def test_a_line_with_heights_across_the_antimeridian_is_cut_without_them(tmp_path):
    from roadsurf.io.formats import split_at_antimeridian

    line = [[179.9999, -16.8, 10.0], [-179.9999, -16.8, 11.0], [-179.9998, -16.8, 12.0]]
    g = split_at_antimeridian({"type": "LineString", "coordinates": line})
    assert g["type"] == "MultiLineString" and all(
        len(p) == 2 for part in g["coordinates"] for p in part
    )
    same = [[10.0, 45.0, 1.0], [10.0001, 45.0, 2.0]]  # no crossing: heights kept as written
    assert split_at_antimeridian({"type": "LineString", "coordinates": same})["coordinates"] == same
