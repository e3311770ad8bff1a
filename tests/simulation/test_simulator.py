"""Image-level simulator: determinism, truth/pixel agreement, drive format, truth files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from pyproj import Transformer

from roadsurf.core.errors import ConfigError, RoadsurfError
from roadsurf.io.drive import load_drive, read_gray
from roadsurf.io.formats import read_csv, read_geojson, read_geotiff
from roadsurf.simulation.scenarios import describe, simulate

# Tiny drives: 240x180 px with the default footprint (fx scaled), 6 frames.
TINY = {"width": 240, "height": 180, "fx": 225.0, "progress": False}


@pytest.fixture(scope="module")
def tiny_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "drive"
    return simulate("potholes", out, seed=11, n_frames=6, **TINY)


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def test_same_seed_same_bytes(tiny_drive: Path, tmp_path: Path) -> None:
    again = simulate("potholes", tmp_path / "again", seed=11, n_frames=6, **TINY)
    a, b = _files(tiny_drive), _files(again)
    assert sorted(a) == sorted(b)
    different = [k for k in a if a[k] != b[k]]
    assert different == []
    other = simulate("potholes", tmp_path / "other", seed=12, n_frames=6, **TINY)
    assert _files(other)["frames/frame_000000.jpg"] != a["frames/frame_000000.jpg"]


def test_drive_passes_loader(tiny_drive: Path) -> None:
    drive = load_drive(tiny_drive)
    assert len(drive.frames) == 6
    assert drive.skipped == []
    assert drive.camera.width == 240 and drive.camera.height_m == pytest.approx(1.1)
    assert drive.gps is not None and drive.obd is not None
    # GPS at a lower rate than the camera, covering the frame times.
    fps = drive.camera.fps
    gps_rate = (len(drive.gps) - 1) / (drive.gps.timestamp_s[-1] - drive.gps.timestamp_s[0])
    assert gps_rate < fps
    assert drive.gps.timestamp_s[0] < drive.frames[0].timestamp_s
    assert drive.gps.timestamp_s[-1] > drive.frames[-1].timestamp_s
    assert read_gray(drive.frames[0]).shape == (180, 240)


def test_truth_files_georeferenced(tiny_drive: Path) -> None:
    truth = tiny_drive / "truth"
    sc = json.loads((truth / "scenario.json").read_text())
    assert sc["crs"].startswith("EPSG:326") and sc["seed"] == 11 and sc["n_frames"] == 6
    with rasterio.open(truth / "height.tif") as src:
        assert str(src.crs) == sc["crs"]
        assert src.dtypes[0] == "float32"
    height, grid, nodata = read_geotiff(truth / "height.tif")
    resid, grid_r, _ = read_geotiff(truth / "residual.tif")
    assert grid == grid_r and nodata is not None and math.isnan(nodata)
    assert 0.002 <= grid.gsd_m <= 0.005
    valid = np.isfinite(height)
    assert 0.05 < valid.mean() < 1.0  # corridor only, nodata outside
    assert np.array_equal(valid, np.isfinite(resid))
    assert abs(float(np.nanmedian(resid))) < 0.003  # the road itself sits at residual ~0

    # poses.csv: lat/lon agree with easting/northing through pyproj.
    rows = read_csv(truth / "poses.csv")
    assert [r["filename"] for r in rows] == [f"frame_{k:06d}.jpg" for k in range(6)]
    tr = Transformer.from_crs(sc["crs"], "EPSG:4326", always_xy=True)
    for r in rows:
        lon, lat = tr.transform(float(r["easting_m"]), float(r["northing_m"]))
        assert lon == pytest.approx(float(r["lon_deg"]), abs=1e-8)
        assert lat == pytest.approx(float(r["lat_deg"]), abs=1e-8)
        q = np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")])
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-6)
        # Camera about 1.1 m above the smooth road (height - residual) below it.
        rc = grid.rowcol_from_xy(np.array([[float(r["easting_m"]), float(r["northing_m"])]]))[0]
        ij = int(round(rc[0])), int(round(rc[1]))
        assert float(r["up_m"]) - (height[ij] - resid[ij]) == pytest.approx(1.1, abs=0.02)

    # Defects: RFC 7946 polygons whose residual really is deep inside.
    fc = read_geojson(truth / "defects.geojson")
    pots = [f for f in fc["features"] if f["properties"]["type"] == "pothole"]
    assert pots, "the potholes scenario must place at least one pothole in 6 frames"
    for f in pots:
        p = f["properties"]
        assert 0.015 <= p["max_depth_m"] <= 0.08 + 1e-9
        assert p["area_m2"] > 0 and p["volume_m3"] > 0 and p["length_m"] >= p["width_m"]
        lon, lat = tr.transform(p["centroid_e_m"], p["centroid_n_m"])
        assert lon == pytest.approx(p["centroid_lon"], abs=1e-8)
        rc = grid.rowcol_from_xy(np.array([[p["centroid_e_m"], p["centroid_n_m"]]]))[0]
        r0, c0 = int(round(rc[0])), int(round(rc[1]))
        win = resid[max(0, r0 - 5) : r0 + 6, max(0, c0 - 5) : c0 + 6]
        if np.isfinite(win).any():
            assert np.nanmin(win) < -0.3 * p["max_depth_m"]
    dist = read_geojson(truth / "distractors.geojson")
    assert all(f["properties"]["max_depth_m"] == 0 for f in dist["features"])

    labels = read_csv(truth / "frame_labels.csv")
    assert len(labels) == 6 and set(labels[0]) == {
        "filename", "defect", "defect_area_cm2", "max_depth_m"
    }  # fmt: skip
    for lab in labels:
        assert int(lab["defect"]) == int(float(lab["defect_area_cm2"]) >= 20.0)


def _project(row: dict[str, str], e: float, n: float, up: float, cam) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q = [float(row[k]) for k in ("qx", "qy", "qz", "qw")]
    R = Rotation.from_quat(q).as_matrix()  # world (E, N, U grid axes) from camera
    C = np.array([float(row["easting_m"]), float(row["northing_m"]), float(row["up_m"])])
    Xc = R.T @ (np.array([e, n, up]) - C)
    uv, _ = cv2.projectPoints(Xc[None], np.zeros(3), np.zeros(3), cam.K, np.asarray(cam.dist))
    return uv.reshape(2)


@pytest.mark.parametrize("distortion", [(0.0,) * 5, (-0.25, 0.08, 0.001, -0.001, 0.0)])
def test_rendered_pothole_appears_where_truth_says(tmp_path: Path, distortion) -> None:
    """Render with one pothole and without it (same seed, nothing else placed): the pixels that
    change must sit where the true pose (and camera.yaml's lens) projects the truth centroid,
    and be darker there."""
    kw = dict(
        TINY, n_potholes=1, n_cracks=0, n_ruts=0, n_lane_markings=0, n_shadows=0, n_oil_stains=0,
        distortion=distortion,
    )  # fmt: skip
    with_p = simulate("potholes", tmp_path / "p", seed=5, n_frames=6, **kw)
    kw["n_potholes"] = 0
    without = simulate("potholes", tmp_path / "n", seed=5, n_frames=6, **kw)
    drive = load_drive(with_p)
    cam = drive.camera
    pot = read_geojson(with_p / "truth" / "defects.geojson")["features"][0]["properties"]
    height, grid, _ = read_geotiff(with_p / "truth" / "height.tif")
    poses = read_csv(with_p / "truth" / "poses.csv")
    rc = grid.rowcol_from_xy(np.array([[pot["centroid_e_m"], pot["centroid_n_m"]]]))[0]
    up = float(height[int(round(rc[0])), int(round(rc[1]))])
    # The frame that sees the pothole centroid closest to the image centre.
    uv = [_project(r, pot["centroid_e_m"], pot["centroid_n_m"], up, cam) for r in poses]
    k = int(np.argmin([np.hypot(u - cam.cx, v - cam.cy) for u, v in uv]))
    u, v = uv[k]
    assert 0 <= u < cam.width and 0 <= v < cam.height
    a = cv2.imread(str(with_p / "frames" / poses[k]["filename"]), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(str(without / "frames" / poses[k]["filename"]), cv2.IMREAD_GRAYSCALE)
    diff = np.abs(a.astype(np.float32) - b.astype(np.float32))
    diff = cv2.GaussianBlur(diff, (0, 0), 2.0)
    changed = diff > 0.5 * diff.max()
    ys, xs = np.nonzero(changed)
    # Centre of the changed region vs the projected truth centroid (px; the outline is irregular).
    radius_px = math.sqrt(pot["area_m2"] / math.pi) * cam.fx / cam.height_m
    assert math.hypot(xs.mean() - u, ys.mean() - v) < max(6.0, 0.5 * radius_px)
    r = max(2, int(0.4 * radius_px))
    ui, vi = int(round(u)), int(round(v))
    inside = a[max(0, vi - r) : vi + r + 1, max(0, ui - r) : ui + r + 1].astype(float).mean()
    same_place = b[max(0, vi - r) : vi + r + 1, max(0, ui - r) : ui + r + 1].astype(float).mean()
    assert inside < same_place - 10  # darker inside the pothole than the intact road
    labels = {x["filename"]: x for x in read_csv(with_p / "truth" / "frame_labels.csv")}
    if pot["max_depth_m"] > 0.02 and pot["area_m2"] > 0.01:
        assert labels[poses[k]["filename"]]["defect"] == "1"
    assert all(x["defect"] == "0" for x in read_csv(without / "truth" / "frame_labels.csv"))


def test_greyscale_png_and_unknown_override(tmp_path: Path) -> None:
    out = simulate("flat", tmp_path / "g", n_frames=2, greyscale=True, image_format="png", **TINY)
    img = cv2.imread(str(out / "frames" / "frame_000000.png"), cv2.IMREAD_UNCHANGED)
    assert img.ndim == 2 and img.dtype == np.uint8
    with pytest.raises(ConfigError):
        simulate("flat", tmp_path / "x", n_frames=2, no_such_param=1)
    with pytest.raises(ConfigError):
        simulate("no-such-scenario", tmp_path / "y")
    assert {"flat", "potholes", "vibration", "rough-gps", "highway", "long", "sample"} <= set(
        describe()
    )


def _gps_errors(drive_dir: Path) -> tuple[np.ndarray, float]:
    """Horizontal GPS error (m) against the true camera centre, and the GPS rate (Hz)."""
    sc = json.loads((drive_dir / "truth" / "scenario.json").read_text())
    poses = read_csv(drive_dir / "truth" / "poses.csv")
    t = np.array([float(r["timestamp_s"]) for r in poses])
    e = np.array([float(r["easting_m"]) for r in poses])
    n = np.array([float(r["northing_m"]) for r in poses])
    gps = read_csv(drive_dir / "gps.csv")
    tg = np.array([float(r["timestamp_s"]) for r in gps])
    tr = Transformer.from_crs("EPSG:4326", sc["crs"], always_xy=True)
    eg, ng = tr.transform([float(r["lon"]) for r in gps], [float(r["lat"]) for r in gps])
    inside = (tg >= t[0]) & (tg <= t[-1])
    err = np.hypot(np.asarray(eg)[inside] - np.interp(tg[inside], t, e),
                   np.asarray(ng)[inside] - np.interp(tg[inside], t, n))  # fmt: skip
    return err, 1.0 / float(np.median(np.diff(tg)))


def test_gps_profiles(tmp_path: Path) -> None:
    kw = dict(TINY, fps=2.0, speed_mps=0.8, n_potholes=0, n_cracks=0)
    rtk = simulate("flat", tmp_path / "rtk", seed=3, n_frames=10, **kw)
    cons = simulate("flat", tmp_path / "cons", seed=3, n_frames=10, gps_profile="consumer", **kw)
    err_rtk, rate_rtk = _gps_errors(rtk)
    err_cons, rate_cons = _gps_errors(cons)
    assert rate_rtk == pytest.approx(5.0) and rate_cons == pytest.approx(1.0)
    assert len(err_rtk) >= 10 and len(err_cons) >= 3
    assert np.median(err_rtk) < 0.1
    assert np.median(err_cons) > 0.3


def test_frame_labels_agree_with_truth_raster(tiny_drive: Path) -> None:
    """The per-frame label (from the rendered rays) agrees with an independent count on
    residual.tif inside the frame footprint (image corners projected with the true pose)."""
    from scipy.spatial.transform import Rotation

    cam = load_drive(tiny_drive).camera
    resid, grid, _ = read_geotiff(tiny_drive / "truth" / "residual.tif")
    labels = read_csv(tiny_drive / "truth" / "frame_labels.csv")
    corners = np.array([[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]]) - 0.5
    n_defect = 0
    for lab, pose in zip(labels, read_csv(tiny_drive / "truth" / "poses.csv"), strict=True):
        R = Rotation.from_quat([float(pose[k]) for k in ("qx", "qy", "qz", "qw")]).as_matrix()
        C = np.array([float(pose[k]) for k in ("easting_m", "northing_m", "up_m")])
        rays = (
            np.column_stack(
                [(corners[:, 0] - cam.cx) / cam.fx, (corners[:, 1] - cam.cy) / cam.fy, np.ones(4)]
            )
            @ R.T
        )
        t = -cam.height_m / rays[:, 2]
        en = C[:2] + t[:, None] * rays[:, :2]
        rc = grid.rowcol_from_xy(en)
        mask = np.zeros(resid.shape, np.uint8)
        cv2.fillPoly(mask, [np.round(rc[:, ::-1]).astype(np.int32)], 1)
        deep = (mask > 0) & (resid < -0.010)
        area_cm2 = deep.sum() * grid.gsd_m**2 * 1e4
        ray_cm2 = float(lab["defect_area_cm2"])
        assert abs(area_cm2 - ray_cm2) <= 0.15 * max(area_cm2, ray_cm2) + 15.0
        n_defect += int(lab["defect"])
    assert n_defect >= 1


def test_cli_simulate_with_overrides(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from roadsurf.cli import app

    out = tmp_path / "cli"
    args = ["simulate", "--scenario", "flat", "--frames", "3", "--out", str(out)]
    for kv in ("width=240", "height=180", "fx=225", "texture=brick", "greyscale=true"):
        args += ["--set", kv]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    drive = load_drive(out)
    assert len(drive.frames) == 3 and drive.camera.width == 240
    sc = json.loads((out / "truth" / "scenario.json").read_text())
    assert sc["params"]["texture"] == "brick" and sc["params"]["greyscale"] is True
    assert CliRunner().invoke(app, ["simulate", "--list"]).exit_code == 0
    # A YAML parameter file, with --set winning over it.
    cfg = tmp_path / "sim.yaml"
    cfg.write_text("texture: grass\nwidth: 240\nheight: 180\nfx: 225.0\nn_oil_stains: 0\n")
    out2 = tmp_path / "cli2"
    res = CliRunner().invoke(
        app,
        ["simulate", "--scenario", "flat", "--frames", "2", "--config", str(cfg), "--out",
         str(out2), "--set", "texture=asphalt"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    params = json.loads((out2 / "truth" / "scenario.json").read_text())["params"]
    assert params["texture"] == "asphalt" and params["width"] == 240
    assert params["n_oil_stains"] == 0
    cfg.write_text("textur: grass\n")
    with pytest.raises(ConfigError, match="sim.yaml"):
        simulate("flat", tmp_path / "cli3", n_frames=2, config=cfg)


@pytest.mark.parametrize("fmt", ["gpx", "nmea"])
def test_gps_log_formats_load_like_csv(tmp_path: Path, fmt: str) -> None:
    """gps.gpx / gps.nmea drives (UNIX-second clock) load to the same fixes as gps.csv."""
    kw = dict(TINY, n_potholes=0, n_cracks=0)
    ref = load_drive(simulate("flat", tmp_path / "csv", seed=4, n_frames=4, **kw))
    drive = load_drive(simulate("flat", tmp_path / fmt, seed=4, n_frames=4, gps_format=fmt, **kw))
    assert drive.gps is not None and ref.gps is not None
    assert drive.gps.source == f"gps.{fmt}" and len(drive.gps) == len(ref.gps)
    offset = drive.frames[0].timestamp_s - ref.frames[0].timestamp_s
    assert offset > 1.7e9  # UNIX seconds (UTC)
    np.testing.assert_allclose(drive.gps.timestamp_s - offset, ref.gps.timestamp_s, atol=2e-3)
    np.testing.assert_allclose(drive.gps.lat_deg, ref.gps.lat_deg, atol=2e-9)
    np.testing.assert_allclose(drive.gps.lon_deg, ref.gps.lon_deg, atol=2e-9)
    np.testing.assert_allclose(drive.gps.alt_m, ref.gps.alt_m, atol=2e-3)
    poses = read_csv(tmp_path / fmt / "truth" / "poses.csv")
    assert float(poses[0]["timestamp_s"]) == pytest.approx(drive.frames[0].timestamp_s)


def test_rerun_into_same_folder_replaces_drive(tmp_path: Path) -> None:
    out = tmp_path / "d"
    simulate("flat", out, n_frames=3, **TINY)
    simulate("flat", out, n_frames=2, gps_format="gpx", **TINY)
    assert not (out / "gps.csv").exists() and (out / "gps.gpx").exists()
    assert sorted(p.name for p in (out / "frames").iterdir()) == [
        "frame_000000.jpg",
        "frame_000001.jpg",
    ]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(RoadsurfError):
        simulate("flat", tmp_path / "other", n_frames=2, **TINY)


def test_pothole_look_and_wall_ranges_are_drawn_from_the_config() -> None:
    """pothole_darken / pothole_power: lighter-than-road potholes and steep walls on demand;
    the defaults draw the same world as before the knobs existed (same random draws)."""
    from roadsurf.simulation.build import build_world
    from roadsurf.simulation.scenarios import make_config

    base = build_world(make_config("potholes"), 202, 20)
    same = build_world(
        make_config("potholes", pothole_darken=(0.55, 0.8), pothole_power=(2.5, 5.0)), 202, 20
    )
    assert [p.darken for p in base.potholes] == [p.darken for p in same.potholes]
    cfg = make_config("potholes", pothole_darken=(1.05, 1.15), pothole_power=(10.0, 12.0))
    other = build_world(cfg, 202, 20)
    assert other.potholes
    assert all(1.05 <= p.darken <= 1.15 for p in other.potholes)
    assert all(10.0 <= p.power <= 12.0 for p in other.potholes)
    assert all(p.darken < 1.0 for p in base.potholes)
    # pothole_size_m / pothole_depth_m: bigger, shallower potholes on demand
    big = build_world(
        make_config("potholes", pothole_size_m=(0.9, 1.3), pothole_depth_m=(0.02, 0.03)), 202, 40
    )

    def extent(p) -> float:  # noqa: ANN001 - a Pothole
        x0, y0, x1, y1 = p.bbox(0.002)
        return max(x1 - x0, y1 - y0)

    assert big.potholes and min(map(extent, big.potholes)) > 0.8
    assert max(map(extent, base.potholes)) < 0.9


def test_a_drive_too_short_for_a_rut_skips_it(tmp_path: Path) -> None:
    """Two small frames leave less than 0.3 m of path: a rut there was a one-point line that
    crashed the truth writer (shapely: 'point array must contain 0 or >1 elements')."""
    out = simulate("varied", tmp_path / "v", n_frames=2, **TINY)
    feats = read_geojson(out / "truth/defects.geojson")["features"]
    types = {f["properties"]["type"] for f in feats}
    assert "rut" not in types


@pytest.mark.parametrize("grade", [0.0, 0.03, -0.05])
def test_the_vehicle_pitches_with_the_road(grade: float) -> None:
    """A vehicle's body lies on its wheels: on a grade it is pitched by the grade (nose up
    uphill), and the truth pose says so. Without vibration the pose's pitch is the road's slope
    between the axles, and the camera's optical axis (nadir) tilts with it."""
    from roadsurf.simulation.build import build_world
    from roadsurf.simulation.scenarios import make_config

    world = build_world(make_config("flat", grade=grade, vibration_deg=0.0), 101, 10)
    t = float(np.mean(world.traj.t))
    pose = world.pose(t)
    assert pose.pitch_rad == pytest.approx(np.arctan(grade), abs=1e-3)
    # the optical axis, world frame: nadir + the road's tilt along the heading
    h = np.radians(pose.heading_deg)
    forward = np.array([np.sin(h), np.cos(h), 0.0])
    axis = pose.R[:, 2]
    assert float(axis @ forward) == pytest.approx(np.sin(np.arctan(grade)), abs=1e-3)
