"""Tilted camera mounts in the simulator (issue 28): poses, footprint, rendering, truth,
camera.yaml, the horizon refusal and the CLI options."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from roadsurf.core.errors import ConfigError
from roadsurf.io.drive import load_drive
from roadsurf.io.formats import read_csv, read_geojson, read_geotiff
from roadsurf.simulation.build import build_world
from roadsurf.simulation.config import SimConfig
from roadsurf.simulation.render import Renderer
from roadsurf.simulation.scenarios import describe, make_config, simulate
from roadsurf.simulation.sensors import form_image

# Small drives with the default field of view (fx scaled with the image).
SMALL = {"width": 160, "height": 120, "fx": 150.0}
TINY = {"width": 240, "height": 180, "fx": 225.0}
QUIET = {"n_potholes": 0, "n_cracks": 0, "n_ruts": 0, "n_lane_markings": 0}
QUIET |= {"n_shadows": 0, "n_oil_stains": 0}


def _pose(row: dict[str, str]) -> tuple[np.ndarray, np.ndarray]:
    """(C, R world_from_cam) of a truth/poses.csv row."""
    R = Rotation.from_quat([float(row[k]) for k in ("qx", "qy", "qz", "qw")]).as_matrix()
    return np.array([float(row[k]) for k in ("easting_m", "northing_m", "up_m")]), R


def _vehicle_axes(heading_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(forward, right) unit vectors on the ground for a grid heading."""
    b = math.radians(heading_deg)
    return np.array([math.sin(b), math.cos(b)]), np.array([math.cos(b), -math.sin(b)])


@pytest.mark.parametrize("pitch", [0.0, 25.0])
def test_footprint_is_a_trapezoid_ahead_of_the_camera(pitch: float) -> None:
    # The mount's geometry alone: no vibration, a flat level road.
    still = {"vibration_deg": 0.0, "height_noise_m": 0.0, "grade": 0.0, "cross_slope": 0.0}
    still |= {"undulation_m": 0.0}
    world = build_world(make_config("flat", mount_pitch_deg=pitch, **SMALL, **still), 3, 3)
    pose = world.pose(float(world.frame_times[1]))
    z = float(world.base(np.array(pose.C[0]), np.array(pose.C[1])))
    fp = Renderer(world).footprint(pose, z)
    fwd, right = _vehicle_axes(pose.heading_deg)
    ahead, side = (fp - pose.C[:2]) @ fwd, (fp - pose.C[:2]) @ right
    tl, tr, br, bl = 0, 4, 8, 12  # the image corners (top = forward)
    far, near = side[tr] - side[tl], side[br] - side[bl]
    h = world.cfg.camera_height_m
    half_v = math.degrees(math.atan(0.5 * world.cfg.height / world.cfg.fx))  # half the view
    if pitch == 0.0:
        assert far == pytest.approx(near, rel=0.02)
        assert ahead.max() == pytest.approx(-ahead.min(), abs=0.01)  # centred under the camera
    else:
        assert far > 1.25 * near  # a trapezoid: the far edge is wider
        assert ahead.min() > 0.0  # all of it ahead of the camera's ground point
        for k, a in ((tl, pitch + half_v), (bl, pitch - half_v)):
            assert ahead[k] == pytest.approx(h * math.tan(math.radians(a)), abs=0.01)


def test_centre_ray_meets_the_road_h_tan_pitch_ahead(tmp_path: Path) -> None:
    """truth/poses.csv: the camera centre does not move with the mount (same trajectory, same
    vehicle heading); the optical axis meets the road h tan(pitch) ahead along the travel."""
    rows = {}
    for pitch in (0.0, 25.0):
        # a level road: on a grade the vehicle, and the axis, pitch with it (test_simulator)
        kw = dict(SMALL, **QUIET, mount_pitch_deg=pitch, grade=0.0, progress=False)
        out = simulate("flat", tmp_path / f"p{pitch:g}", seed=8, n_frames=4, **kw)
        rows[pitch] = read_csv(out / "truth" / "poses.csv")
    h = 1.1
    for pitch, poses in rows.items():
        for k, row in enumerate(poses[:-1]):
            ref = rows[0.0][k]
            for key in ("easting_m", "northing_m", "up_m", "heading_deg", "roll_deg"):
                assert row[key] == ref[key]
            C, R = _pose(row)
            axis = R[:, 2]  # camera z in the world
            hit = C[:2] + axis[:2] * (-h / axis[2])
            travel = _pose(poses[k + 1])[0][:2] - C[:2]
            travel /= np.linalg.norm(travel)
            off = hit - C[:2]
            assert float(off @ travel) == pytest.approx(h * math.tan(math.radians(pitch)), abs=0.02)
            assert abs(travel[0] * off[1] - travel[1] * off[0]) < 0.02  # not to the side
    q0 = [float(rows[0.0][0][k]) for k in ("qw", "qx", "qy", "qz")]
    q25 = [float(rows[25.0][0][k]) for k in ("qw", "qx", "qy", "qz")]
    angle = 2 * math.degrees(math.acos(min(1.0, abs(float(np.dot(q0, q25))))))
    assert angle == pytest.approx(25.0, abs=0.1)


def test_mount_yaw_turns_the_camera_not_the_vehicle(tmp_path: Path) -> None:
    kw = dict(SMALL, **QUIET, mount_pitch_deg=20.0, progress=False)
    a = read_csv(simulate("flat", tmp_path / "a", seed=8, n_frames=2, **kw) / "truth/poses.csv")
    kw["mount_yaw_deg"] = 10.0
    b = read_csv(simulate("flat", tmp_path / "b", seed=8, n_frames=2, **kw) / "truth/poses.csv")
    assert [r["heading_deg"] for r in a] == [r["heading_deg"] for r in b]
    (_, Ra), (_, Rb) = _pose(a[0]), _pose(b[0])
    # Seen from above, the optical axis turns clockwise by about the yaw.
    az = [math.degrees(math.atan2(R[0, 2], R[1, 2])) for R in (Ra, Rb)]
    assert (az[1] - az[0] + 180) % 360 - 180 == pytest.approx(10.0, abs=1.0)


def _project(row: dict[str, str], X: np.ndarray, cam) -> tuple[np.ndarray, float]:
    """Raw pixel of world point X through the true pose and camera.yaml; and its depth."""
    C, R = _pose(row)
    Xc = R.T @ (X - C)
    uv, _ = cv2.projectPoints(Xc[None], np.zeros(3), np.zeros(3), cam.K, np.asarray(cam.dist))
    return uv.reshape(2), float(Xc[2])


@pytest.mark.parametrize(("pitch", "roll", "yaw"), [(25.0, 0.0, 0.0), (35.0, 6.0, -8.0)])
def test_rendered_pothole_appears_where_truth_projects(tmp_path: Path, pitch, roll, yaw) -> None:
    """With one pothole and without it (same seed): the pixels that change sit where the true
    pose projects the truth centroid, and are darker there."""
    kw = dict(TINY, **QUIET, progress=False)
    kw |= {"n_potholes": 1, "mount_pitch_deg": pitch, "mount_roll_deg": roll, "mount_yaw_deg": yaw}
    with_p = simulate("potholes", tmp_path / "p", seed=5, n_frames=8, **kw)
    kw["n_potholes"] = 0
    without = simulate("potholes", tmp_path / "n", seed=5, n_frames=8, **kw)
    cam = load_drive(with_p).camera
    pot = read_geojson(with_p / "truth" / "defects.geojson")["features"][0]["properties"]
    height, grid, _ = read_geotiff(with_p / "truth" / "height.tif")
    rc = grid.rowcol_from_xy(np.array([[pot["centroid_e_m"], pot["centroid_n_m"]]]))[0]
    X = np.array(
        [pot["centroid_e_m"], pot["centroid_n_m"], height[int(rc[0] + 0.5), int(rc[1] + 0.5)]]
    )
    poses = read_csv(with_p / "truth" / "poses.csv")
    uvz = [_project(r, X, cam) for r in poses]
    k = int(np.argmin([np.hypot(uv[0] - cam.cx, uv[1] - cam.cy) for uv, _ in uvz]))
    (u, v), depth = uvz[k]
    assert 0 <= u < cam.width and 0 <= v < cam.height
    a = cv2.imread(str(with_p / "frames" / poses[k]["filename"]), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(str(without / "frames" / poses[k]["filename"]), cv2.IMREAD_GRAYSCALE)
    diff = cv2.GaussianBlur(np.abs(a.astype(np.float32) - b.astype(np.float32)), (0, 0), 2.0)
    ys, xs = np.nonzero(diff > 0.5 * diff.max())
    radius_px = math.sqrt(pot["area_m2"] / math.pi) * cam.fx / depth
    assert math.hypot(xs.mean() - u, ys.mean() - v) < max(6.0, 0.5 * radius_px)
    r, ui, vi = max(2, int(0.4 * radius_px)), int(round(u)), int(round(v))
    win = (slice(max(0, vi - r), vi + r + 1), slice(max(0, ui - r), ui + r + 1))
    assert a[win].mean() < b[win].mean() - 10  # darker inside the pothole


def test_frame_labels_use_the_tilted_ground_area(tmp_path: Path) -> None:
    """A tilted pixel covers t² / (fx² |d_z|) of road: the rays' defect area agrees with a
    count on residual.tif inside the frame's trapezoid (corners through the true pose onto
    height.tif). Per frame loosely (a pothole's near rim hides part of it from flat rays),
    over the drive tightly."""
    out = simulate(
        "potholes", tmp_path / "d", seed=11, n_frames=10, mount_pitch_deg=45.0, progress=False,
        **TINY,
    )  # fmt: skip
    cam = load_drive(out).camera
    resid, grid, _ = read_geotiff(out / "truth" / "residual.tif")
    height = read_geotiff(out / "truth" / "height.tif")[0]
    labels = read_csv(out / "truth" / "frame_labels.csv")
    corners = np.array([[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]]) - 0.5
    rays_cam = np.column_stack(
        [(corners[:, 0] - cam.cx) / cam.fx, (corners[:, 1] - cam.cy) / cam.fy, np.ones(4)]
    )
    totals = np.zeros(2)
    for lab, row in zip(labels, read_csv(out / "truth" / "poses.csv"), strict=True):
        C, R = _pose(row)
        rays = rays_cam @ R.T
        z = np.full(4, C[2] - cam.height_m)
        for _ in range(3):  # onto the road surface, metres ahead
            en = C[:2] + ((z - C[2]) / rays[:, 2])[:, None] * rays[:, :2]
            rc = np.round(grid.rowcol_from_xy(en)).astype(int)
            rc = np.clip(rc, 0, np.array(height.shape) - 1)
            z = np.where(np.isfinite(height[rc[:, 0], rc[:, 1]]), height[rc[:, 0], rc[:, 1]], z)
        mask = np.zeros(resid.shape, np.uint8)
        cv2.fillPoly(mask, [rc[:, ::-1].astype(np.int32)], 1)
        raster_cm2 = ((mask > 0) & (resid < -0.010)).sum() * grid.gsd_m**2 * 1e4
        ray_cm2 = float(lab["defect_area_cm2"])
        assert abs(raster_cm2 - ray_cm2) <= 0.5 * max(raster_cm2, ray_cm2) + 15.0
        totals += (raster_cm2, ray_cm2)
    assert totals[0] > 2000.0
    assert totals[1] == pytest.approx(totals[0], rel=0.05)


def test_camera_yaml_gets_the_mount_only_with_write_mount(tmp_path: Path) -> None:
    kw = dict(SMALL, **QUIET, mount_pitch_deg=20.0, mount_roll_deg=3.0, mount_yaw_deg=-2.0)
    hidden = simulate("flat", tmp_path / "h", n_frames=2, progress=False, **kw)
    assert "mount" not in (hidden / "camera.yaml").read_text()
    assert load_drive(hidden).camera.mount_deg is None
    given = simulate("flat", tmp_path / "g", n_frames=2, progress=False, write_mount=True, **kw)
    text = (given / "camera.yaml").read_text()
    assert "mount_pitch_deg: 20.0" in text and "mount_yaw_deg: -2.0" in text
    assert load_drive(given).camera.mount_deg == (20.0, 3.0, -2.0)
    nadir = simulate("flat", tmp_path / "n", n_frames=2, progress=False, **SMALL, **QUIET)
    assert "mount" not in (nadir / "camera.yaml").read_text()


def test_a_view_reaching_the_horizon_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "x"
    with pytest.raises(ConfigError) as err:
        simulate("flat", out, n_frames=2, mount_pitch_deg=45.0, fx=150.0, width=160, height=240)
    msg = str(err.value)
    assert all(k in msg for k in ("mount_pitch_deg=45", "fx=150", "height=240"))
    assert "mount_pitch_deg <=" in msg  # says what would work
    assert not out.exists()  # refused before writing anything
    with pytest.raises(ConfigError, match="below the horizon"):
        build_world(SimConfig(mount_pitch_deg=58.0), 1, 2)
    # on a 20 % climb the vehicle pitches nose-up 11°: a 55° mount a level road takes is refused
    SimConfig(mount_pitch_deg=55.0, grade=0.0).check_view()
    SimConfig(mount_pitch_deg=55.0, grade=-0.2).check_view()
    with pytest.raises(ConfigError, match="on a grade of 0.2"):
        build_world(SimConfig(mount_pitch_deg=55.0, grade=0.2), 1, 2)
    with pytest.raises(ConfigError, match="mount_pitch_deg"):
        make_config("flat", mount_pitch_deg=70.0)  # outside the field's range
    make_config("flat", mount_pitch_deg=45.0, mount_roll_deg=15.0, mount_yaw_deg=-15.0)


def test_tilted_motion_blur_follows_the_image_motion() -> None:
    """Near rows of a tilted view move (and blur) faster than far rows; nadir rows alike."""
    h, w = 120, 160
    stripes = 0.5 + 0.4 * np.sin(2 * np.pi * np.arange(h) / 8.0)  # along the travel
    radiance = np.repeat(np.repeat(stripes[:, None, None], w, 1), 3, 2).astype(np.float32)
    quiet = dict(SMALL, noise_sigma=0.0, shot_noise=0.0, vignetting=0.0, exposure_time_s=0.006)

    def contrast(pitch: float) -> tuple[float, float]:
        cfg = SimConfig(**quiet, mount_pitch_deg=pitch)
        img = form_image(radiance, cfg, 6.0, 1.0, np.random.default_rng(0))[..., 0]
        col = img[:, w // 2].astype(float)
        return float(np.ptp(col[5:25])), float(np.ptp(col[90:110]))  # far (top), near

    top0, bottom0 = contrast(0.0)  # a 5 px blur
    assert top0 == pytest.approx(bottom0, abs=3)
    top, bottom = contrast(45.0)  # 1 px at the top, 4 px near the bottom
    assert top > 1.3 * bottom
    assert top > 1.5 * top0  # far rows blur less than under a nadir camera


def test_tilted_scenario_is_potholes_tilted_with_5cm_gps() -> None:
    assert "tilted" in describe()
    tilted, potholes = make_config("tilted"), make_config("potholes")
    assert tilted == dataclasses.replace(potholes, mount_pitch_deg=25.0, gps_sigma_m=0.05)
    assert not tilted.write_mount


def test_cli_mount_options(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from roadsurf.cli import app

    out = tmp_path / "cli"
    args = ["simulate", "--scenario", "flat", "--frames", "2", "--out", str(out)]
    args += ["--mount-pitch", "15", "--mount-roll", "-2", "--mount-yaw", "3", "--write-mount"]
    for kv in ("width=160", "height=120", "fx=150"):
        args += ["--set", kv]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    params = json.loads((out / "truth" / "scenario.json").read_text())["params"]
    assert (params["mount_pitch_deg"], params["mount_roll_deg"]) == (15.0, -2.0)
    assert params["mount_yaw_deg"] == 3.0 and params["write_mount"] is True
    assert load_drive(out).camera.mount_deg == (15.0, -2.0, 3.0)
