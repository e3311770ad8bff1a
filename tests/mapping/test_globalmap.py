"""Global map on a rendered synthetic drive with a known pothole: outputs read back with real
readers (plyfile, rasterio, json) and checked against the known geometry and texture."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import rasterio
from plyfile import PlyData

from roadsurf.core.geometry import ExportFrame, enu_from_lla, lla_from_utm
from roadsurf.io.drive import load_drive
from roadsurf.io.formats import GridSpec
from roadsurf.mapping import globalmap, poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.raster import grid_mean, interpolate_to_grid
from roadsurf.reconstruction.types import PairResult
from tests.mapping.synth import REF, make_pair, make_synthetic, texture, write_drive, write_images

POT_ENU = np.array([2.0, 3.3])  # pothole centre in the synthetic REF ENU frame (m)
POT_DEPTH = 0.03
POT_SIGMA = 0.08


def road(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return -POT_DEPTH * np.exp(
        -((x - POT_ENU[0]) ** 2 + (y - POT_ENU[1]) ** 2) / (2 * POT_SIGMA**2)
    )


# the sparse surface's own rules (5 mm grid, one cloud point per fused point, capped fill);
# the dense surface (the default) has its tests in test_dense_fuse.py
CFG = MappingConfig(gps_sigma_m=0.02, tile_px=256, surface_source="sparse")


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object, object]:
    root = tmp_path_factory.mktemp("map")
    syn = make_synthetic(n=50, seed=21, gps_hz=5.0, road_z=road)
    syn = write_images(syn, root / "drive")
    run = root / "run"
    traj = poses.run(CFG, syn.drive, syn.pairs, run)
    prod = globalmap.run(CFG, syn.drive, syn.pairs, traj, run)
    return run, syn, prod


def _ref_enu_from_utm(xy: np.ndarray, epsg: int = 32617) -> np.ndarray:
    lla = lla_from_utm(xy[:, 0], xy[:, 1], epsg)
    return enu_from_lla(lla[:, 0], lla[:, 1], 0.0, REF)[:, :2]


def test_cloud_ply_is_georeferenced_with_residuals(mapped) -> None:
    run, syn, prod = mapped
    v = PlyData.read(str(run / "cloud.ply"))["vertex"].data
    names = v.dtype.names
    assert {"x", "y", "z", "red", "green", "blue", "residual_m"} <= set(names)
    assert v.dtype["x"] == np.float64 and v.dtype["red"] == np.uint8
    assert v.dtype["residual_m"] == np.float32
    assert len(v) == prod.n_points > 1000
    crs = json.loads((run / "reference.json").read_text())["reference"]["crs"]
    assert crs == "EPSG:32617"
    enu = _ref_enu_from_utm(np.column_stack([v["x"], v["y"]]))
    # every point lies on the road under the true path, within the footprint width
    path = syn.world_from_cam[:, :2, 3]
    d = np.min(np.linalg.norm(enu[:, None] - path[None], axis=2), axis=1)
    assert np.percentile(d, 99) < 0.9
    r = np.asarray(v["residual_m"], float)
    inside = np.linalg.norm(enu - POT_ENU, axis=1) < 0.05
    flat = np.linalg.norm(enu - POT_ENU, axis=1) > 0.5
    assert inside.sum() > 5
    assert np.median(np.abs(r[inside] - road(enu[inside, 0], enu[inside, 1]))) < 0.003
    assert np.min(r[inside]) < -0.02
    assert np.median(np.abs(r[flat])) < 0.001
    # colours come from the images (texture at the point's position)
    rgb = np.column_stack([v["red"], v["green"], v["blue"]]).astype(float)
    exp = texture(enu[:, 0], enu[:, 1]).astype(float)
    assert np.median(np.abs(rgb - exp)) < 25


def test_surface_and_mosaic_share_a_grid_and_match_truth(mapped) -> None:
    run, syn, prod = mapped
    with rasterio.open(run / "surface.tif") as s, rasterio.open(run / "mosaic.tif") as m:
        assert s.crs.to_epsg() == 32617 and m.crs == s.crs
        assert s.transform == m.transform and s.shape == m.shape
        assert abs(s.transform.a - 0.005) < 1e-12
        assert s.dtypes[0] == "float32" and m.count == 3 and m.dtypes[0] == "uint8"
        assert np.isnan(s.nodata)
        res = s.read(1)
        mos = np.moveaxis(m.read(), 0, 2)
        T = s.transform
    fin = np.isfinite(res)
    assert 0.05 < fin.mean() < 0.9  # the corridor, not the bounding box
    rows, cols = np.nonzero(fin)
    xy = np.column_stack([T.c + (cols + 0.5) * T.a, T.f + (rows + 0.5) * T.e])
    enu = _ref_enu_from_utm(xy)
    truth = road(enu[:, 0], enu[:, 1])
    flat = np.abs(truth) < 1e-4
    assert np.mean(np.abs(res[fin][flat] - truth[flat])) < 0.0015
    deep = truth < -0.02
    assert deep.sum() > 50
    assert np.mean(np.abs(res[fin][deep] - truth[deep])) < 0.005
    # mosaic georeferencing: colours at imaged pixels equal the texture at their position
    has = mos.any(axis=2)
    r2, c2 = np.nonzero(has)
    pick = np.linspace(0, len(r2) - 1, 4000).astype(int)
    xy2 = np.column_stack([T.c + (c2[pick] + 0.5) * T.a, T.f + (r2[pick] + 0.5) * T.e])
    enu2 = _ref_enu_from_utm(xy2)
    exp = texture(enu2[:, 0], enu2[:, 1]).astype(float)
    got = mos[r2[pick], c2[pick]].astype(float)
    assert np.median(np.abs(got - exp)) < 20
    assert has.sum() >= fin.sum()


def test_vrt_and_tiles_cover_the_same_data(mapped) -> None:
    run, _, prod = mapped
    assert prod.n_tiles > 2
    tiles = sorted((run / "tiles").glob("surface_*.tif"))
    assert len(tiles) == prod.n_tiles == len(prod.tiles)
    rep = json.loads((run / "map_report.json").read_text())
    for t in rep["tiles"]:
        assert (run / t["surface"]).is_file() and (run / t["mosaic"]).is_file()
        with rasterio.open(run / t["surface"]) as ts:
            assert np.allclose(list(ts.bounds), t["bounds"])
    with rasterio.open(run / "surface.vrt") as v, rasterio.open(run / "surface.tif") as s:
        assert v.shape == s.shape and v.transform == s.transform and v.crs == s.crs
        assert v.tags()["VERTICAL_DATUM"] == s.tags()["VERTICAL_DATUM"]  # the VRT's own tags
        assert v.tags()["units"] == "m"
        a, b = v.read(1), s.read(1)
    np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
    np.testing.assert_allclose(a[np.isfinite(a)], b[np.isfinite(b)])
    # the corridor-bounded reader gives the same pixels as the monolithic file
    from roadsurf.mapping.raster import iter_tiles

    n_valid = 0
    for grid, data in iter_tiles(run, "surface"):
        assert data.shape == (grid.height, grid.width)
        n_valid += int(np.isfinite(data).sum())
    assert n_valid == int(np.isfinite(b).sum())
    for name in ("mosaic_preview.png", "surface_preview.png", "map_points.npz"):
        assert (run / name).stat().st_size > 0
    with np.load(run / "map_points.npz") as z:
        assert {"xyz", "rgb", "residual_m", "frame_index"} <= set(z.files)


def test_seams_between_tiles_do_not_show(mapped) -> None:
    run, _, _ = mapped
    with rasterio.open(run / "surface.tif") as s:
        res = s.read(1)
    tp = CFG.tile_px
    steps = []
    for k in range(tp, res.shape[1] - 1, tp):  # vertical tile borders
        a, b = res[:, k - 1], res[:, k]
        ok = np.isfinite(a) & np.isfinite(b)
        if ok.sum() > 20:
            steps.append(np.median(np.abs(a[ok] - b[ok])))
    assert steps and max(steps) < 0.0005


def test_resume_skips_and_overwrite_rebuilds(mapped) -> None:
    run, syn, _ = mapped
    from roadsurf.mapping.types import load_trajectory

    traj = load_trajectory(run)
    m0 = os.stat(run / "surface.tif").st_mtime_ns
    globalmap.run(CFG, syn.drive, syn.pairs, traj, run)
    assert os.stat(run / "surface.tif").st_mtime_ns == m0


def test_a_stopped_rewrite_or_a_truncated_raster_is_rebuilt(
    mapped, tmp_path: Path, monkeypatch
) -> None:
    """map_report.json goes before the map is rewritten (a rewrite stopped half way left the
    old record beside a sparse cloud and rasters on two grids, and a resume reused them); a
    raster truncated since is rebuilt (detection crashed reading it)."""
    import dataclasses
    import shutil

    from roadsurf.mapping.types import load_trajectory

    run0, syn, _ = mapped
    run = tmp_path / "run"
    shutil.copytree(run0, run)
    traj = load_trajectory(run)
    surf = run / "surface.tif"
    surf.write_bytes(surf.read_bytes()[: surf.stat().st_size // 2])
    globalmap.run(CFG, syn.drive, syn.pairs, traj, run)
    with rasterio.open(surf) as a, rasterio.open(run0 / "surface.tif") as b:
        np.testing.assert_array_equal(a.read(), b.read())
    tile = run / json.loads((run / "map_report.json").read_text())["tiles"][0]["surface"]
    tile.write_bytes(tile.read_bytes()[:100])  # a tile too (surface.vrt reads it)
    globalmap.run(CFG, syn.drive, syn.pairs, traj, run)
    with rasterio.open(tile) as t:
        assert np.isfinite(t.read(1)).any()

    def stopped(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(globalmap, "build_map", stopped)
    other = dataclasses.replace(CFG, gsd_m=CFG.gsd_m * 1.25)
    with pytest.raises(KeyboardInterrupt):
        globalmap.run(other, syn.drive, syn.pairs, traj, run)
    assert not (run / "map_report.json").exists()
    (run / "map_report.json").write_text("[1, 2]")  # valid JSON, not a record: rebuilt
    monkeypatch.undo()
    m0 = surf.stat().st_mtime_ns
    globalmap.run(CFG, syn.drive, syn.pairs, traj, run)
    assert surf.stat().st_mtime_ns != m0


def test_raster_tiles_on_one_or_more_threads_are_identical(mapped, tmp_path: Path) -> None:
    """raster_workers only changes who computes a tile: the files are the same, bit for bit."""
    import dataclasses

    from roadsurf.mapping.types import load_trajectory

    run, syn, prod = mapped
    assert CFG.raster_workers > 1 and prod.n_tiles > 2
    one = dataclasses.replace(CFG, raster_workers=1)
    prod1 = globalmap.run(one, syn.drive, syn.pairs, load_trajectory(run), tmp_path / "run1")
    assert prod1.n_tiles == prod.n_tiles and prod1.tiles == prod.tiles
    for name in ("surface.tif", "mosaic.tif"):
        with rasterio.open(run / name) as a, rasterio.open(tmp_path / "run1" / name) as b:
            np.testing.assert_array_equal(a.read(), b.read())
    # and a finished map is not rebuilt because the thread count changed
    m0 = os.stat(tmp_path / "run1" / "surface.tif").st_mtime_ns
    globalmap.run(CFG, syn.drive, syn.pairs, load_trajectory(run), tmp_path / "run1")
    assert os.stat(tmp_path / "run1" / "surface.tif").st_mtime_ns == m0


def test_broken_frame_mid_drive_is_skipped(tmp_path: Path) -> None:
    syn = make_synthetic(n=24, seed=31, gps_hz=5.0)
    write_drive(syn, tmp_path / "drive", broken=(12,))
    drive = load_drive(tmp_path / "drive")
    assert len(drive.frames) == 23
    assert any("000012" in s.file for s in drive.skipped)
    # the reconstruction stage pairs consecutive VALID frames: (11, 13) spans the broken one
    true_of = {f"{i:06d}.png": syn.world_from_cam[i] for i in range(24)}
    rng = np.random.default_rng(0)
    pairs: list[PairResult] = []
    for a, b in zip(drive.frames[:-1], drive.frames[1:], strict=True):
        p = make_pair(a.index, true_of[a.filename], true_of[b.filename], drive.camera, rng)
        p.frame_a, p.frame_b, p.index_b = a.filename, b.filename, b.index
        pairs.append(p)
    run = tmp_path / "run"
    traj = poses.run(CFG, drive, pairs, run)
    assert len(traj) == 23 and "000012.png" not in traj.filenames
    prod = globalmap.run(CFG, drive, pairs, traj, run)
    with rasterio.open(run / "mosaic.tif") as m:
        assert m.read(1).any()
    assert prod.n_points > 500


def test_gridding_helpers() -> None:
    grid = GridSpec("EPSG:32617", 0.0, 1.0, 0.01, 100, 100)
    rng = np.random.default_rng(0)
    xy = rng.uniform(0.05, 0.95, (3000, 2))
    v = 0.1 * xy[:, 0] - 0.05 * xy[:, 1]
    out = interpolate_to_grid(xy, v, grid, max_edge_m=0.1)
    rr, cc = np.nonzero(np.isfinite(out))
    cen = grid.xy_from_rowcol(rr, cc)
    np.testing.assert_allclose(out[rr, cc], 0.1 * cen[:, 0] - 0.05 * cen[:, 1], atol=1e-5)
    assert np.isnan(out[0, 0])  # outside the points: a hole, not extrapolation
    m = grid_mean(xy, v, grid)
    assert np.isfinite(m).sum() > 0.8 * 90 * 90 * (1 - np.exp(-0.33))
    assert ExportFrame.for_reference(REF).crs == "EPSG:32617"


def test_no_gps_map_stays_in_the_local_frame(tmp_path: Path) -> None:
    syn = make_synthetic(n=16, seed=41, with_gps=False)
    syn = write_images(syn, tmp_path / "drive")
    run = tmp_path / "run"
    traj = poses.run(CFG, syn.drive, syn.pairs, run)
    prod = globalmap.run(CFG, syn.drive, syn.pairs, traj, run)
    assert prod.crs is None and not (run / "trajectory.geojson").exists()
    with rasterio.open(run / "surface.tif") as s:
        assert s.crs is None
        assert np.isfinite(s.read(1)).sum() > 1000
    # no CRS: every raster says in a tag what its metres are
    for name in ("surface", "mosaic", "surface_nobs", "surface_sigma"):
        for path in [run / f"{name}.tif", run / f"{name}.vrt"]:
            if path.exists():
                with rasterio.open(path) as r:
                    assert "never lon/lat" in r.tags().get("COORDINATES", ""), path
    v = PlyData.read(str(run / "cloud.ply"))["vertex"].data
    # local ENU metres around the first camera, not UTM
    assert np.max(np.abs(v["x"])) < 50 and np.max(np.abs(v["y"])) < 50


def test_consecutive_overlap_and_its_warning() -> None:
    """Share of each footprint the next one sees; a median below min_frame_overlap warns."""
    from roadsurf.mapping.overlap import check_frame_overlap, consecutive_overlap
    from roadsurf.mapping.types import MapProducts

    def square(y0: float) -> np.ndarray:  # 1 m x 0.8 m footprint, as a 5 x 5 point grid
        X, Y = np.meshgrid(np.linspace(0, 1, 5), np.linspace(y0, y0 + 0.8, 5))
        return np.column_stack([X.ravel(), Y.ravel()])

    fps = [square(0.0), square(0.24), square(0.48), np.zeros((0, 2)), square(1.0)]
    ov = consecutive_overlap(fps)
    assert ov[:2] == pytest.approx([0.7, 0.7])
    assert np.isnan(ov[2]) and np.isnan(ov[3])
    prod = MapProducts(Path("."), None, 0.005)
    check_frame_overlap(MappingConfig(), fps, prod)
    assert prod.frame_overlap["median"] == pytest.approx(0.7) and not prod.warnings
    fast = [square(0.56 * i) for i in range(6)]  # 30 % overlap: the map would be strips
    check_frame_overlap(MappingConfig(), fast, prod)
    assert prod.frame_overlap["median"] == pytest.approx(0.3)
    assert len(prod.warnings) == 1 and "overlap by only 30%" in prod.warnings[0]


def test_rasters_and_detection_run_under_a_bounded_gdal_block_cache(
    mapped, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 31 #10: GDAL's block cache (5 % of RAM by default) kept every block written to the
    open surface.tif/mosaic.tif, and read from surface.tif by detection, so memory grew with the
    drive's length. Both stages now run with the cache capped."""
    import dataclasses

    from rasterio.env import getenv

    from roadsurf.detection import stage as detection_stage
    from roadsurf.detection.config import DetectionConfig
    from roadsurf.mapping.raster import GDAL_CACHE_BYTES

    run, syn, _ = mapped
    seen: dict[str, object] = {}

    def spy(name: str, fn):
        def wrapped(*a, **k):
            try:
                seen[name] = getenv().get("GDAL_CACHEMAX")
            except Exception:  # noqa: BLE001 - no rasterio environment at all
                seen[name] = None
            return fn(*a, **k)

        return wrapped

    monkeypatch.setattr(globalmap, "rasterise", spy("globalmap", globalmap.rasterise))
    monkeypatch.setattr(
        detection_stage, "segment_windows", spy("detection", detection_stage.segment_windows)
    )
    traj = poses.run(CFG, syn.drive, syn.pairs, run)
    globalmap.run(dataclasses.replace(CFG, overwrite=True), syn.drive, syn.pairs, traj, run)
    detection_stage.run(DetectionConfig(overwrite=True), syn.drive, syn.pairs, traj, run)
    assert seen == {"globalmap": GDAL_CACHE_BYTES, "detection": GDAL_CACHE_BYTES}
