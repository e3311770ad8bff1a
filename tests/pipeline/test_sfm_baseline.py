"""The pycolmap SfM baseline (roadsurf.pipeline.sfm) on a small simulated drive, read back
with real readers."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from roadsurf.core.camera import Camera
from roadsurf.io.drive import load_drive
from roadsurf.io.formats import LOCAL_CRS, read_csv, read_geojson, read_geotiff, read_ply
from roadsurf.mapping.raster import corridor_tiles
from roadsurf.pipeline.sfm import run, run_from_paths
from roadsurf.pipeline.sfm.colmap_run import colmap_camera
from roadsurf.pipeline.sfm.config import SfmBaselineConfig
from roadsurf.pipeline.sfm.fits import robust_fit_2d
from roadsurf.pipeline.sfm.georef import _fit_vertical_tilt, _neighbour_heading_dev
from roadsurf.pipeline.sfm.surface import local_surface, surface_raster

N_FRAMES = 12
BLANK = "blank"  # the frame we replace with a textureless image


@pytest.fixture(scope="module")
def sim_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scenarios = pytest.importorskip("roadsurf.simulation.scenarios")
    root = tmp_path_factory.mktemp("sfm") / "drive"
    scenarios.simulate(
        "flat",
        root,
        n_frames=N_FRAMES,
        progress=False,
        width=320,
        height=240,
        fx=300.0,
        speed_mps=3.0,
    )
    # The last frame becomes a uniform grey image: valid for the loader, but SIFT finds nothing,
    # so COLMAP cannot register it and the report must say why.
    last = sorted((root / "frames").iterdir())[-1]
    cv2.imwrite(str(last), np.full((240, 320), 128, np.uint8))
    return root


@pytest.fixture(scope="module")
def sfm_out(sim_drive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sfm_out")
    run(SfmBaselineConfig(num_threads=2), sim_drive, out)
    return out


def test_registers_and_explains_the_rest(sim_drive: Path, sfm_out: Path) -> None:
    rep = json.loads((sfm_out / "report.json").read_text())
    names = [f.filename for f in load_drive(sim_drive).frames]
    assert rep["n_images"] == N_FRAMES
    assert 0 < rep["registered"] <= N_FRAMES - 1
    blank = names[-1]
    assert blank in rep["not_registered_reason"]
    assert "SIFT features" in rep["not_registered_reason"][blank]
    # every valid frame is either registered or explained
    assert rep["registered"] + len(rep["not_registered_reason"]) == N_FRAMES
    assert (sfm_out / "colmap" / "database.db").is_file()
    assert any((sfm_out / "colmap" / "sparse").iterdir())
    # the metric scale came from the camera height: cameras sit ~h above the fitted planes
    assert rep["scale"]["alpha_m_per_unit"] > 0
    assert rep["scale"]["d_c_rel_spread"] < 0.1


def test_outputs_read_back_in_utm(sim_drive: Path, sfm_out: Path) -> None:
    rep = json.loads((sfm_out / "report.json").read_text())
    truth = json.loads((sim_drive / "truth" / "scenario.json").read_text())
    assert rep["crs"] == truth["crs"] and rep["crs"].startswith("EPSG:326")

    ply = read_ply(sfm_out / "cloud.ply")  # plyfile
    assert ply["xyz"].dtype == np.float64 and len(ply["xyz"]) > 100
    assert ply["rgb"].dtype == np.uint8
    assert ply["residual_m"].dtype == np.float32
    # a flat road: residuals are a few mm, not decimetres
    assert float(np.percentile(np.abs(ply["residual_m"]), 90)) < 0.02

    surf, grid, nodata = read_geotiff(sfm_out / "surface.tif")  # rasterio
    assert grid.crs == rep["crs"] and surf.dtype == np.float32
    assert nodata is not None and math.isnan(nodata)
    assert np.isfinite(surf).sum() > 50 and np.isnan(surf).any()
    # the raster sits on the truth raster's ground (same UTM area)
    _, tgrid, _ = read_geotiff(sim_drive / "truth" / "residual.tif")
    centre = tgrid.xy_from_rowcol(np.array([tgrid.height / 2]), np.array([tgrid.width / 2]))
    r, c = grid.rowcol_from_xy(centre)[0]
    assert 0 <= r < grid.height and 0 <= c < grid.width
    # on the tile lattice of `roadsurf run` (origin on multiples of tile_px x gsd_m)
    tile_m = rep["config"]["tile_px"] * grid.gsd_m
    assert abs(grid.x0_m / tile_m - round(grid.x0_m / tile_m)) < 1e-6
    # points lie inside the surface grid
    rc = grid.rowcol_from_xy(ply["xyz"][:, :2])
    assert (rc >= -1).all() and (rc[:, 0] <= grid.height).all() and (rc[:, 1] <= grid.width).all()


def test_trajectory_close_to_gps_and_truth(sim_drive: Path, sfm_out: Path) -> None:
    from roadsurf.core.geometry import utm_from_lla

    rep = json.loads((sfm_out / "report.json").read_text())
    epsg = int(rep["crs"].split(":")[1])
    fc = read_geojson(sfm_out / "trajectory.geojson")
    kinds = [f["geometry"]["type"] for f in fc["features"]]
    assert kinds[0] == "LineString" and kinds.count("Point") == rep["registered"]
    pts = [f for f in fc["features"] if f["geometry"]["type"] == "Point"]
    for f in pts:
        assert {"filename", "timestamp_s", "heading_deg", "source"} <= set(f["properties"])
        assert f["properties"]["source"] == "visual"
    truth = {r["filename"]: r for r in read_csv(sim_drive / "truth" / "poses.csv")}
    lonlat = np.array([f["geometry"]["coordinates"] for f in pts])
    est = utm_from_lla(lonlat[:, 1], lonlat[:, 0], epsg)
    ref = np.array(
        [
            [float(truth[f["properties"]["filename"]][k]) for k in ("easting_m", "northing_m")]
            for f in pts
        ]
    )
    err = np.linalg.norm(est - ref, axis=1)
    assert err.max() < 0.5, err  # RTK-grade simulated GPS: centimetres expected
    dh = [
        (f["properties"]["heading_deg"] - float(truth[f["properties"]["filename"]]["heading_deg"]))
        for f in pts
    ]
    assert max(abs((d + 180) % 360 - 180) for d in dh) < 5.0
    assert rep["gps_alignment"]["rms_m"] < 0.5
    # the GPS-implied scale agrees with the camera-height scale
    assert abs(rep["gps_alignment"]["gps_scale_over_height_scale"] - 1) < 0.1


def test_resume_and_no_gps_local_frame(sim_drive: Path, sfm_out: Path, tmp_path: Path) -> None:
    # A drive without GPS, resuming from the finished COLMAP folder (same images and settings).
    d2 = tmp_path / "nogps"
    shutil.copytree(sim_drive, d2, ignore=shutil.ignore_patterns("gps.csv", "truth"))
    out2 = tmp_path / "out"
    out2.mkdir()
    shutil.copytree(sfm_out / "colmap", out2 / "colmap")
    res = run(SfmBaselineConfig(num_threads=2), d2, out2)
    rep = res.report
    assert "features_s" not in rep["timings_s"] and "mapping_s" not in rep["timings_s"]
    assert res.crs is None and rep["crs"] is None
    assert not (out2 / "trajectory.geojson").exists()
    ply = read_ply(out2 / "cloud.ply")
    # local metric frame: coordinates within a few metres of the first camera
    assert np.abs(ply["xyz"]).max() < 20
    surf, grid, _ = read_geotiff(out2 / "surface.tif")
    assert grid.crs == LOCAL_CRS and np.isfinite(surf).any()
    assert rep["registered"] == json.loads((sfm_out / "report.json").read_text())["registered"]


def test_cli_command(sim_drive: Path, sfm_out: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from roadsurf.cli import app

    out = tmp_path / "cli"
    shutil.copytree(sfm_out / "colmap", out / "colmap")  # resume: the CLI test stays fast
    r = CliRunner().invoke(app, ["sfm-baseline", str(sim_drive), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "images registered" in r.output and "not registered:" in r.output
    assert (out / "report.json").is_file() and (out / "cloud.ply").is_file()


# --------------------------------------------------------------------------- unit helpers


def test_colmap_camera_principal_point_convention() -> None:
    cam = Camera(320, 240, 300.0, 301.0, 159.5, 119.5, 1.1, 15.0)
    model, params = colmap_camera(cam)
    assert model == "PINHOLE" and params == "300.0,301.0,160.0,120.0"
    cam_d = Camera(320, 240, 300.0, 300.0, 159.5, 119.5, 1.1, 15.0, (-0.1, 0.01, 0.0, 0.0, 0.0))
    assert colmap_camera(cam_d)[0] == "OPENCV"
    cam_k3 = Camera(320, 240, 300.0, 300.0, 159.5, 119.5, 1.1, 15.0, (-0.1, 0.0, 0.0, 0.0, 0.01))
    assert colmap_camera(cam_k3)[0] == "FULL_OPENCV"


def test_robust_fit_2d_recovers_rotation_despite_outliers() -> None:
    rng = np.random.default_rng(2)
    src = np.column_stack([np.linspace(0, 20, 40), 0.3 * np.sin(np.linspace(0, 3, 40))])
    a = math.radians(37.0)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    dst = src @ R.T + [100.0, -50.0] + rng.normal(0, 0.02, src.shape)
    dst[5] += [8.0, -3.0]  # a GPS jump
    fit, inl = robust_fit_2d(src, dst, False, 3.0)
    assert not inl[5] and inl.sum() >= 35
    assert abs(math.degrees(fit.yaw_rad) - 37.0) < 0.2
    assert np.allclose(fit.t, [100.0, -50.0], atol=0.05) and fit.scale == 1.0
    assert abs(robust_fit_2d(src * 0.5, dst, True, 3.0)[0].scale - 2.0) < 0.01


def test_local_residuals_and_raster() -> None:
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 4, (8000, 2))
    z = 0.03 * xy[:, 0] + 0.2 * np.sin(xy[:, 1] / 3) + rng.normal(0, 0.0005, len(xy))
    hole = np.linalg.norm(xy - [2.0, 2.0], axis=1) < 0.25
    z[hole] -= 0.04
    xyz = np.column_stack([xy, z])
    res = local_surface(SfmBaselineConfig(), xyz).residual(xyz)
    ok = np.isfinite(res)
    assert ok.mean() > 0.99
    assert abs(np.median(res[hole]) + 0.04) < 0.006
    assert np.percentile(np.abs(res[~hole & ok]), 90) < 0.004
    cfg = SfmBaselineConfig(gsd_m=0.1, tile_px=16)
    xy_utm = xy + [500_003.0, 4_400_007.0]
    img, grid = surface_raster(xy_utm, res, cfg, "EPSG:32617")
    assert img.shape == (grid.height, grid.width) and img.dtype == np.float32
    rc = grid.rowcol_from_xy(np.array([[500_005.0, 4_400_009.0]])).round().astype(int)[0]
    assert img[rc[0], rc[1]] < -0.03
    # the grid of `roadsurf run`'s surface.tif: the mapping tile lattice (origin on tile multiples)
    lat = corridor_tiles(xy_utm, "EPSG:32617", 0.1, 16)[0]
    assert grid == lat.full_grid and grid.x0_m % 1.6 == pytest.approx(0.0, abs=1e-6)
    # a too-large raster is coarsened, never allocated
    big = SfmBaselineConfig(gsd_m=0.01, tile_px=16, max_raster_px=10**6)
    _, g2 = surface_raster(np.array([[0.0, 0.0], [1000.0, 1000.0]]), np.zeros(2), big, None)
    assert g2.width * g2.height <= 10**6 and g2.crs == LOCAL_CRS


def test_vertical_tilt_follows_good_gps_altitude_only() -> None:
    rng = np.random.default_rng(4)
    s = np.linspace(0, 20, 40)
    c_h = np.column_stack([0.6 * s, 0.8 * s, np.zeros_like(s)])  # heading ~37°, flat in z
    gps = c_h.copy()
    gps[:, 2] = 5.0 + 0.03 * s + rng.normal(0, 0.01, len(s))  # 3% climb, RTK-grade altitude
    ok = np.ones(len(s), bool)
    cfg = SfmBaselineConfig()
    R, pivot, tilt = _fit_vertical_tilt(c_h, gps, ok, cfg)
    assert abs(tilt - math.degrees(math.atan(0.03))) < 0.1
    moved = (c_h - pivot) @ R.T + pivot
    dz = gps[:, 2] - moved[:, 2]
    assert np.std(dz) < 0.02  # the climb is followed
    noisy = gps.copy()
    noisy[:, 2] = 5.0 + rng.normal(0, 2.0, len(s))  # consumer altitude: no tilt from noise
    assert _fit_vertical_tilt(c_h, noisy, ok, cfg) is None


def test_neighbour_heading_deviation_flags_a_flipped_pose() -> None:
    h = np.array([10.0, 11.0, 9.5, 190.0, 10.5, 359.0 + 12.0 - 360.0, 10.0])
    dev = _neighbour_heading_dev(h)
    assert dev[3] > 170 and np.all(np.delete(dev, 3) < 5)


def test_changed_image_invalidates_resume(sim_drive: Path, sfm_out: Path, tmp_path: Path) -> None:
    """Same filenames but a re-rendered image: the features (and later steps) are recomputed."""
    d2 = tmp_path / "drive"
    shutil.copytree(sim_drive, d2)  # copy2 keeps mtimes: unchanged files still resume
    out2 = tmp_path / "out"
    shutil.copytree(sfm_out / "colmap", out2 / "colmap")
    first = sorted((d2 / "frames").iterdir())[0]
    img = cv2.imread(str(first))
    cv2.imwrite(str(first), cv2.flip(img, 1))
    rep = run(SfmBaselineConfig(num_threads=2), d2, out2).report
    assert "features_s" in rep["timings_s"] and "mapping_s" in rep["timings_s"]


def _blank_drive(root: Path, n: int = 4) -> Path:
    (root / "frames").mkdir(parents=True)
    (root / "camera.yaml").write_text(
        "model: pinhole\nwidth: 64\nheight: 48\nfx: 60\nfy: 60\ncx: 31.5\ncy: 23.5\n"
        "height_m: 1.1\nfps: 10\n"
    )
    rows = ["filename,timestamp_s"]
    for i in range(n):
        cv2.imwrite(str(root / "frames" / f"{i:03d}.png"), np.full((48, 64), 128, np.uint8))
        rows.append(f"{i:03d}.png,{0.1 * i}")
    (root / "frames.csv").write_text("\n".join(rows) + "\n")
    return root


def test_textureless_drive_fails_with_reasons(tmp_path: Path) -> None:
    from roadsurf.core.errors import RoadsurfError

    drive = _blank_drive(tmp_path / "d")
    with pytest.raises(RoadsurfError, match=r"no usable model.*SIFT features"):
        run(SfmBaselineConfig(num_threads=1), drive, tmp_path / "out")
    assert (tmp_path / "out" / "colmap" / "database.db").is_file()


def test_config_file_rejects_unknown_keys(tmp_path: Path) -> None:
    from roadsurf.core.errors import ConfigError

    cfg = tmp_path / "c.yaml"
    cfg.write_text("sfm_baseline:\n  overlap: 3\n  ovrlap: 4\n")
    with pytest.raises(ConfigError, match="ovrlap"):
        run_from_paths(tmp_path / "d", tmp_path / "o", config_path=cfg)
