"""Drive loader, camera.yaml: every validation rule in docs/formats.md."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive import load_drive
from tests.io.drive_fixtures import H, W, camera_yaml, make_drive

# --------------------------------------------------------------------------- camera.yaml


def test_missing_camera_yaml(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").unlink()
    with pytest.raises(DriveFormatError, match="camera.yaml not found"):
        load_drive(root)


def test_missing_camera_key(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(fx=None))
    with pytest.raises(DriveFormatError, match=r"missing required key\(s\) \['fx'\]"):
        load_drive(root)


def test_ill_typed_camera_key_names_line(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(width="wide"))
    with pytest.raises(DriveFormatError, match=r"camera.yaml:2: camera.yaml 'width'"):
        load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(height_m=-1))
    with pytest.raises(DriveFormatError, match=r":9: .*'height_m' must be > 0"):
        load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(dist="[1, 2]"))
    with pytest.raises(DriveFormatError, match="'dist' must be a list of 5 numbers"):
        load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(model="fisheye"))
    with pytest.raises(DriveFormatError, match="'model' must be 'pinhole'"):
        load_drive(root)


def test_integral_float_size_accepted(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(width=f"{W}.0"))
    assert load_drive(root).camera.width == W
    (root / "camera.yaml").write_text(camera_yaml(width=f"{W}.5"))
    with pytest.raises(DriveFormatError, match="positive integer"):
        load_drive(root)


def test_unknown_camera_key(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml() + "focal: 3\n")
    with pytest.raises(DriveFormatError, match=r":11: unknown key\(s\) \['focal'\]"):
        load_drive(root)


def test_bad_yaml_syntax(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text("width: [64\nheight: 48\n")
    with pytest.raises(DriveFormatError, match="not valid YAML"):
        load_drive(root)


def test_mount_angles_load(tmp_path: Path) -> None:
    """`roadsurf calibrate --ground` writes mount angles; the loader keeps them (the poses use
    them and check them against the drive: tests/mapping/test_mount.py)."""
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(mount_pitch_deg=25.0, mount_roll_deg=1.0))
    d = load_drive(root)
    assert d.camera.mount_deg == (25.0, 1.0, 0.0)
    assert not d.warnings
    (root / "camera.yaml").write_text(camera_yaml())
    assert load_drive(root).camera.mount_deg is None


def test_mount_angle_out_of_range_names_key(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(mount_pitch_deg=-5.0))
    load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(mount_pitch_deg=125.0))
    with pytest.raises(DriveFormatError, match=r"mount_pitch_deg.*outside \[-90, 90\] degrees"):
        load_drive(root)


def test_camera_height_in_cm_is_refused_with_the_metre_value(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(height_m=110))
    with pytest.raises(DriveFormatError, match=r"height_m' = 110.*1.1 m"):
        load_drive(root)


def test_focal_length_in_mm_is_refused_with_the_field_of_view(tmp_path: Path) -> None:
    """fx typed in mm (6 for a 640 px image's 600 px) gives a 158° view: refused, naming the key,
    its line and the unit; a wide but real lens (120°) loads."""
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(fx=6.0, fy=60.0))
    with pytest.raises(DriveFormatError, match=r"camera.yaml:\d+.*'fx' = 6 px.*field of view.*px"):
        load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(fx=60.0, fy=2000.0))
    with pytest.raises(DriveFormatError, match=r"'fy' = 2000 px gives a 1.4° field"):
        load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(fx=0.5 * W / 1.73, fy=60.0))  # 120°
    assert load_drive(root).camera.fx == pytest.approx(0.5 * W / 1.73)


def test_readout_time_loads(tmp_path: Path) -> None:
    """Optional readout_s: the rolling shutter's readout time (s); absent = global shutter."""
    root = make_drive(tmp_path / "d")
    assert load_drive(root).camera.readout_s == 0.0
    (root / "camera.yaml").write_text(camera_yaml(readout_s=0.03))
    assert load_drive(root).camera.readout_s == 0.03
    (root / "camera.yaml").write_text(camera_yaml(readout_s=0))
    assert load_drive(root).camera.readout_s == 0.0


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (-0.01, r"camera.yaml:11: camera.yaml 'readout_s' = -0.01 is outside \[0, 0.2\) s"),
        (20, r"camera.yaml:11: camera.yaml 'readout_s' = 20.0 is outside \[0, 0.2\) s.*ms typed"),
        (0.2, r":11: .*'readout_s' = 0.2 is outside"),
        ("fast", r":11: camera.yaml 'readout_s' must be a number, got 'fast'"),
        (0.15, r":11: .*'readout_s' = 0.15 s is longer than one frame period \(1 / fps = 0.1 s"),
    ],
)
def test_readout_time_out_of_range_names_file_line_and_value(
    tmp_path: Path, value: object, message: str
) -> None:
    root = make_drive(tmp_path / "d")  # fps 10: a frame period of 0.1 s
    (root / "camera.yaml").write_text(camera_yaml(readout_s=value))
    with pytest.raises(DriveFormatError, match=message):
        load_drive(root)


# --------------------------------------------------------------------------- mask


def _write_mask(path: Path, shape: tuple[int, int], masked_rows: int) -> None:
    import cv2
    import numpy as np

    m = np.full(shape, 255, np.uint8)
    m[shape[0] - masked_rows :] = 0  # the bonnet along the bottom edge
    assert cv2.imwrite(str(path), m)


def test_mask_loads_and_enters_the_fingerprint_only_when_given(tmp_path: Path) -> None:
    """Optional mask: an image of the camera's size, 0 = ignore; its digest joins the stage
    fingerprints, and a camera without one fingerprints as before the key existed."""
    import dataclasses

    root = make_drive(tmp_path / "d")
    cam = load_drive(root).camera
    assert cam.mask is None
    skip = ("mask", "gps_antenna_m")  # the antenna enters the poses' fingerprint only
    expected = {k: v for k, v in dataclasses.asdict(cam).items() if k not in skip}
    assert cam.fingerprint_fields() == expected
    _write_mask(root / "mask.png", (H, W), 12)
    (root / "camera.yaml").write_text(camera_yaml(mask="mask.png"))
    drive = load_drive(root)
    m = drive.camera.mask
    assert m is not None and m.shape == (H, W)
    assert m.masked_share == pytest.approx(12 / H)
    assert not m.usable[-1].any() and m.usable[0].all()
    assert drive.camera.fingerprint_fields()["mask"] == m.digest
    assert not any("mask" in w for w in drive.warnings)
    # a colour mask counts any nonzero channel as usable; an absolute path works too
    import cv2
    import numpy as np

    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[: H - 12, :, 1] = 200
    cv2.imwrite(str(tmp_path / "rgb.png"), rgb)
    (root / "camera.yaml").write_text(camera_yaml(mask=str(tmp_path / "rgb.png")))
    assert load_drive(root).camera.mask == m
    # RGBA: painted black on an opaque layer, or cut out as transparency: both mask
    rgba = np.full((H, W, 4), 255, np.uint8)
    rgba[H - 12 :, :, :3] = 0
    cv2.imwrite(str(root / "mask.png"), rgba)
    (root / "camera.yaml").write_text(camera_yaml(mask="mask.png"))
    assert load_drive(root).camera.mask == m
    rgba[H - 12 :, :, :3] = 255
    rgba[H - 12 :, :, 3] = 0
    cv2.imwrite(str(root / "mask.png"), rgba)
    assert load_drive(root).camera.mask == m
    # an empty value is no mask
    (root / "camera.yaml").write_text(camera_yaml(mask=None).rstrip() + "\nmask:\n")
    assert load_drive(root).camera.mask is None


def test_mask_hiding_most_of_the_image_warns(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    _write_mask(root / "mask.png", (H, W), 30)
    (root / "camera.yaml").write_text(camera_yaml(mask="mask.png"))
    drive = load_drive(root)
    assert any("mask hides 62%" in w for w in drive.warnings)


@pytest.mark.parametrize(
    ("value", "shape", "rows", "message"),
    [
        (
            "none.png",
            None,
            0,
            r"camera.yaml:11: camera.yaml 'mask' names .*none.png, which does not",
        ),
        (
            "mask.png",
            (H + 2, W),
            4,
            r":11: .*mask.png is 64 x 50 px, the camera's images are 64 x 48",
        ),
        ("mask.png", (H, W), H - 2, r":11: .*leaves 4.2% of the image usable.*inverted"),
        (12, None, 0, r":11: camera.yaml 'mask' must be the path of an image"),
        ("junk.png", None, 0, r":11: .*junk.png cannot be read as an image"),
    ],
)
def test_bad_mask_names_file_line_and_what_to_do(
    tmp_path: Path, value: object, shape: tuple[int, int] | None, rows: int, message: str
) -> None:
    root = make_drive(tmp_path / "d")
    if shape is not None:
        _write_mask(root / "mask.png", shape, rows)
    (root / "junk.png").write_bytes(b"not an image")
    (root / "camera.yaml").write_text(camera_yaml(mask=value))
    with pytest.raises(DriveFormatError, match=message):
        load_drive(root)
