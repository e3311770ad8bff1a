"""`roadsurf calibrate` on boards rendered with known intrinsics, distortion and mount
(issue 28 target: focal length within 0.2 %, camera height within 2 mm)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from roadsurf.core.camera import Camera
from roadsurf.core.geometry import world_from_cam, world_from_vehicle_rotation
from roadsurf.io.drive.camera_yaml import load_camera
from roadsurf.reconstruction.calibration import synthetic
from roadsurf.reconstruction.calibration.board import parse_board
from roadsurf.reconstruction.calibration.command import calibrate_command
from roadsurf.reconstruction.calibration.detect import Detection
from roadsurf.reconstruction.calibration.errors import BoardSpecError, CalibrationError
from roadsurf.reconstruction.calibration.intrinsics import (
    CalibrationLimits,
    calibrate_detections,
)
from roadsurf.reconstruction.calibration.mount import (
    mount_angles_deg,
    mount_from_ground,
    rotation_vehicle_from_cam,
)

CAM = Camera(640, 480, 500.0, 502.0, 322.5, 238.0, 1.25, 10.0, (-0.2, 0.05, 0.001, -0.0005, 0.0))
BOARD = "checkerboard:9x6:0.025"
GROUND_BOARD = "checkerboard:9x6:0.08"  # a larger board on the road, as in practice
HEIGHT, PITCH, ROLL, YAW = 1.25, 25.0, 1.0, 0.0


def _render_set(folder: Path, n: int, seed: int, blur: float = 0.4) -> list[Path]:
    spec = parse_board(BOARD)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, T in enumerate(synthetic.calibration_poses(CAM, spec, n, seed=seed, fill=0.5)):
        img = synthetic.render_board(CAM, spec, T, blur_sigma_px=blur, noise_grey=1.0, seed=i)
        paths.append(folder / f"board_{i:02d}.png")
        cv2.imwrite(str(paths[-1]), img)
    return paths


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("calib")
    paths = _render_set(root / "boards", 18, seed=4)
    blank = root / "boards" / "zz_blank.png"  # no board: listed and skipped
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    gspec = parse_board(GROUND_BOARD)
    T = synthetic.ground_pose(gspec, HEIGHT, PITCH, ROLL, YAW)
    ground = root / "ground.png"
    cv2.imwrite(str(ground), synthetic.render_board(CAM, gspec, T, 3, 0.4, 1.0, seed=99))
    res = calibrate_command(
        [root / "boards"], BOARD, root / "out", ground=ground, ground_board=GROUND_BOARD, fps=15
    )
    return res, paths, root


def test_focal_length_and_principal_point(calibrated) -> None:
    res = calibrated[0]
    K = res.intrinsics.K
    assert abs(K[0, 0] / CAM.fx - 1) < 0.002
    assert abs(K[1, 1] / CAM.fy - 1) < 0.002
    assert abs(K[0, 2] - CAM.cx) < 2.0 and abs(K[1, 2] - CAM.cy) < 2.0
    assert res.intrinsics.rms_px < 0.2
    assert "zz_blank.png" in " ".join(res.intrinsics.skipped)


def test_distortion_reproduces_pixel_positions(calibrated) -> None:
    """Over the image area the boards covered, the estimated lens model maps every pixel to
    the true ray up to a homography (K and a rotation, which trade off with the poses) within
    0.1 px."""
    intr = calibrated[0].intrinsics
    u, v = np.meshgrid(np.linspace(0, 639, 40), np.linspace(0, 479, 30))
    px = np.column_stack([u.ravel(), v.ravel()])
    mask = np.zeros((480, 640), np.uint8)
    for h in intr.board_hulls:
        cv2.fillConvexPoly(mask, np.round(h).astype(np.int32), 1)
    px = px[mask[px[:, 1].astype(int), px[:, 0].astype(int)] > 0]
    n_true = CAM.normalised_from_raw_px(px)
    n_est = cv2.undistortPoints(px.reshape(-1, 1, 2), intr.K, intr.dist).reshape(-1, 2)
    H, _ = cv2.findHomography(n_true, n_est, 0)
    mapped = cv2.perspectiveTransform(n_true.reshape(-1, 1, 2), H).reshape(-1, 2)
    err_px = np.linalg.norm(mapped - n_est, axis=1) * CAM.fx
    assert len(px) > 500
    assert err_px.max() < 0.1


def test_camera_height_and_mount_angles(calibrated) -> None:
    m = calibrated[0].mount
    assert abs(m.height_m - HEIGHT) < 0.002
    assert abs(m.pitch_deg - PITCH) < 0.2
    assert abs(m.roll_deg - ROLL) < 0.2
    assert abs(m.yaw_deg - YAW) < 0.2


def test_writes_camera_yaml_and_report(calibrated) -> None:
    res = calibrated[0]
    text = res.camera_yaml.read_text()
    for key in ("fx:", "dist:", "height_m: 1.2", "fps: 15", "mount_pitch_deg: 2"):
        assert key in text
    rep = json.loads(res.report_json.read_text())
    assert rep["board"] == BOARD and rep["images_used"] == 18
    assert len(rep["per_image"]) == 18 and rep["ground"]["height_m"] == pytest.approx(1.25, 0.01)
    assert "Mount: height 1.2" in " ".join(res.lines)


def test_camera_yaml_without_mount_loads_as_a_drive_camera(calibrated, tmp_path: Path) -> None:
    paths = calibrated[1]
    res = calibrate_command(paths[:8], BOARD, tmp_path, fps=10, height_m=1.1)
    cam = load_camera(res.camera_yaml)
    assert cam.height_m == 1.1 and cam.fps == 10.0 and cam.width == 640
    assert cam.fx == pytest.approx(res.intrinsics.K[0, 0], abs=1e-5)
    assert "mount_" not in res.camera_yaml.read_text()
    with pytest.raises(CalibrationError, match="--overwrite"):
        calibrate_command(paths[:8], BOARD, tmp_path, fps=10, height_m=1.1)
    # recalibrating over it keeps what a calibration does not measure
    cv2.imwrite(str(tmp_path / "mask.png"), np.full((480, 640), 255, np.uint8))
    with res.camera_yaml.open("a") as f:
        f.write("readout_s: 0.02\nmask: mask.png\ngps_antenna_m: [-1.5, 0.3, 0.9]\n")
    again = calibrate_command(paths[:8], BOARD, tmp_path, height_m=1.1, overwrite=True)
    cam = load_camera(again.camera_yaml)
    assert cam.readout_s == 0.02 and cam.fps == 10.0 and cam.mask is not None
    assert cam.gps_antenna_m == (-1.5, 0.3, 0.9)
    assert any("Kept readout_s, mask, gps_antenna_m, fps" in line for line in again.lines)


def test_too_few_images_are_refused(calibrated, tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"found in 3 image\(s\).*at least 5") as e:
        calibrate_command(calibrated[1][:3], BOARD, tmp_path)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "camera.yaml").exists()


def test_blurred_images_are_refused(tmp_path: Path) -> None:
    paths = _render_set(tmp_path / "blur", 6, seed=7, blur=9.0)
    with pytest.raises(CalibrationError, match="Take more sharp") as e:
        calibrate_command(paths, BOARD, tmp_path / "out")
    assert "board not found" not in str(e.value) and "skipped" in str(e.value)


def _projected(poses: list[np.ndarray], noise_px: float) -> list[Detection]:
    """Board corners projected with the true camera plus Gaussian noise (no rendering)."""
    obj = parse_board(BOARD).object_points()
    rng = np.random.default_rng(0)
    dets = []
    for T in poses:
        u, v = CAM.project(obj.astype(float) @ T[:3, :3].T + T[:3, 3])
        px = np.column_stack([u, v]) + rng.normal(0, noise_px, (len(u), 2))
        dets.append(Detection(px.astype(np.float32), obj))
    return dets


def test_poor_fit_and_frontal_boards_are_refused() -> None:
    spec = parse_board(BOARD)
    poses = synthetic.calibration_poses(CAM, spec, 10, seed=1, fill=0.5)
    names = [f"b{i}" for i in range(10)]
    with pytest.raises(CalibrationError, match=r"RMS reprojection error is \d"):
        calibrate_detections(names, _projected(poses, 1.5), (640, 480), CalibrationLimits())
    frontal = []
    for T in poses:
        F = T.copy()
        F[:3, :3] = np.eye(3)
        frontal.append(F)
    with pytest.raises(CalibrationError, match="tilted"):
        calibrate_detections(names, _projected(frontal, 0.05), (640, 480), CalibrationLimits())


def test_charuco_ground_board_any_way_round() -> None:
    """A ChArUco board on the road, turned by 180°: same height and angles, yaw 2°."""
    spec = parse_board("charuco:7x5:0.12:0.09:DICT_5X5_100")
    T = synthetic.ground_pose(spec, 1.1, 30.0, -1.0, 2.0)
    x0, y0, x1, y1 = spec.outline_m()
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])  # board rotated 180° about its centre
    turn[:2, 3] = [x0 + x1, y0 + y1]
    img = synthetic.render_board(CAM, spec, T @ turn, blur_sigma_px=0.4, noise_grey=1.0)
    m = mount_from_ground(img, spec, CAM.K, CAM.dist_array)
    assert abs(m.height_m - 1.1) < 0.002
    assert (m.pitch_deg, m.roll_deg, m.yaw_deg) == pytest.approx((30.0, -1.0, 2.0), abs=0.2)


def test_mount_convention_matches_world_from_cam() -> None:
    """Zero angles = the nadir camera; pitch and roll as in core.geometry.world_from_cam."""
    pitch, roll = math.radians(20.0), math.radians(-3.0)
    R = world_from_vehicle_rotation(30.0) @ rotation_vehicle_from_cam(20.0, -3.0, 0.0)
    assert np.allclose(R, world_from_cam(30.0, roll, pitch)[:3, :3])
    assert mount_angles_deg(rotation_vehicle_from_cam(25.0, 1.5, -4.0)) == pytest.approx(
        (25.0, 1.5, -4.0)
    )
    axis = rotation_vehicle_from_cam(25.0, 0.0, 0.0)[:, 2]  # optical axis: forward = -y
    assert axis[1] < 0 and axis[2] > 0


@pytest.mark.parametrize(
    "text, needle",
    [
        ("checkerboard:9x6", "takes 2 fields"),
        ("checkerboard:9by6:0.025", "COLSxROWS"),
        ("checkerboard:9x6:25", "in metres"),
        ("checkerboard:2x6:0.025", "at least 3x3"),
        ("circles:9x6:0.025", "unknown board type"),
        ("charuco:7x5:0.04:0.05:DICT_5X5_100", "smaller than the square"),
        ("charuco:7x5:0.04:0.03:DICT_9X9", "unknown ArUco dictionary"),
        ("charuco:20x20:0.04:0.03:DICT_4X4_50", "needs 200"),
    ],
)
def test_bad_board_spec_is_one_line(text: str, needle: str) -> None:
    with pytest.raises(BoardSpecError, match=needle) as e:
        parse_board(text)
    assert "\n" not in str(e.value) and "Expected checkerboard:" in str(e.value)


def test_board_spec_parses() -> None:
    spec = parse_board("charuco:7x5:0.04:0.03:dict_5x5_100")
    assert spec.text == "charuco:7x5:0.04:0.03:DICT_5X5_100" and spec.n_corners == 24
    assert parse_board(" checkerboard:9x6:0.025 ").object_points().shape == (54, 3)


def test_cli_camera_yaml_with_mount_loads_as_a_drive_camera(calibrated) -> None:
    """`roadsurf calibrate` end to end through the CLI: the camera.yaml it writes, mount
    angles included, is accepted by the drive loader."""
    import subprocess
    import sys

    root = calibrated[2]
    gspec = parse_board(GROUND_BOARD)
    ground = root / "ground.png"
    assert ground.is_file() and gspec is not None
    out = root / "cli_out"
    r = subprocess.run(
        [sys.executable, "-m", "roadsurf", "calibrate", str(root / "boards"), "--board", BOARD,
         "--out", str(out), "--ground", str(ground), "--ground-board", GROUND_BOARD, "--fps", "15"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    cam = load_camera(out / "camera.yaml")
    assert cam.mount_deg is not None and cam.mount_deg[0] == pytest.approx(PITCH, abs=0.2)
    assert cam.height_m == pytest.approx(HEIGHT, abs=0.002)
    bad = subprocess.run(
        [sys.executable, "-m", "roadsurf", "calibrate", str(root / "boards"), "--board", "chess",
         "--out", str(root / "x")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
