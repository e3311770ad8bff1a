"""Drive loader, frames.csv and frames/: every validation rule in docs/formats.md."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from roadsurf.core.errors import DriveFormatError, FrameReadError
from roadsurf.io.drive import load_drive, read_gray, read_image
from tests.io.drive_fixtures import H, W, camera_yaml, make_drive, texture

# --------------------------------------------------------------------------- happy paths


def test_valid_drive_loads(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "d"))
    assert len(d.frames) == 5
    assert [f.index for f in d.frames] == list(range(5))
    assert d.camera.width == W and d.camera.fx == 60.0 and d.camera.height_m == 1.1
    assert d.gps is not None and len(d.gps) >= 3 and d.gps.source == "gps.csv"
    assert np.all(np.isfinite(d.gps.hdop))
    assert d.skipped == []
    assert d.obd is None


def test_read_image_rgb_and_gray_for_colour_and_grey_files(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", n=2, ext=".png")
    grey = texture(7, gray=True)
    cv2.imwrite(str(root / "frames" / "000001.png"), grey)
    d = load_drive(root)
    colour = read_image(d.frames[0])
    assert colour.shape == (H, W, 3) and colour.dtype == np.uint8
    # cv2 wrote BGR; read_image must return RGB.
    bgr = texture(0)
    assert np.array_equal(colour, bgr[:, :, ::-1])
    g3 = read_image(d.frames[1])
    assert g3.shape == (H, W, 3) and np.array_equal(g3[:, :, 0], grey)
    g = read_gray(d.frames[1])
    assert g.shape == (H, W) and g.dtype == np.uint8 and np.array_equal(g, grey)
    assert read_gray(d.frames[0]).shape == (H, W)


def test_jpeg_drive_loads(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "d", ext=".jpg"))
    assert len(d.frames) == 5 and read_image(d.frames[2]).shape == (H, W, 3)


def test_dist_optional_defaults_to_zero(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(dist=None))
    cam = load_drive(root).camera
    assert cam.dist == (0.0,) * 5 and not cam.has_distortion
    (root / "camera.yaml").write_text(camera_yaml(dist="[-0.1, 0.01, 0.0, 0.0, 0.001]"))
    assert load_drive(root).camera.dist == (-0.1, 0.01, 0.0, 0.0, 0.001)


# --------------------------------------------------------------------------- frames


def test_non_increasing_frame_timestamps(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    lines = (root / "frames.csv").read_text().splitlines()
    lines[3] = lines[3].split(",")[0] + ",0.1"  # same as line 3 (file line numbers are 1-based)
    (root / "frames.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(
        DriveFormatError, match=r"frames.csv:4: frame timestamp 0.1 is not after.*stereo rig"
    ):
        load_drive(root)


def test_non_numeric_frame_timestamp(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    lines = (root / "frames.csv").read_text().splitlines()
    lines[2] = lines[2].split(",")[0] + ",abc"
    (root / "frames.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DriveFormatError, match=r"frames.csv:3: timestamp_s 'abc' is not a number"):
        load_drive(root)


def test_bad_frames_header(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    txt = (root / "frames.csv").read_text().replace("filename,timestamp_s", "file,time")
    (root / "frames.csv").write_text(txt)
    with pytest.raises(DriveFormatError, match=r"frames.csv:1: header"):
        load_drive(root)


def test_filenames_with_frames_prefix_are_accepted(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    txt = (root / "frames.csv").read_text().replace("\n0000", "\nframes/0000")
    (root / "frames.csv").write_text(txt)
    d = load_drive(root)
    assert len(d.frames) == 5 and d.frames[0].filename == "000000.png"
    assert any("'frames/'" in w for w in d.warnings)


def test_row_pointing_to_missing_image_is_skipped(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "frames" / "000002.png").unlink()
    d = load_drive(root)
    assert [f.filename for f in d.frames] == [
        "000000.png",
        "000001.png",
        "000003.png",
        "000004.png",
    ]
    assert [f.index for f in d.frames] == [0, 1, 2, 3]
    (s,) = d.skipped
    assert s.file == "frames.csv" and s.line == 4 and "does not exist" in s.reason
    assert any("missing" in w for w in d.warnings)


def test_all_images_missing_is_an_error(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", n=2)
    for p in (root / "frames").iterdir():
        p.unlink()
    with pytest.raises(
        DriveFormatError, match=r"empty drive.* E.g. frames.csv:2: image frames/000000.png does"
    ):
        load_drive(root)


def test_webp_frames_say_why_the_drive_is_empty(tmp_path: Path) -> None:
    """Every row a .webp: the error names the first row and its reason, not only 'empty'."""
    root = make_drive(tmp_path / "d", n=2, ext=".webp")
    with pytest.raises(DriveFormatError, match=r"E.g. frames.csv:2: frames/000000.webp is not a"):
        load_drive(root)


@pytest.mark.parametrize("ext", [".tif", ".tiff", ".bmp"])
def test_tiff_and_bmp_frames_load(tmp_path: Path, ext: str) -> None:

    from roadsurf.io.drive import read_gray

    root = make_drive(tmp_path / "d", n=3, ext=ext)
    if ext == ".tif":  # a 16-bit TIFF, as industrial cameras write
        p = root / "frames" / "000001.tif"
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(p), img.astype(np.uint16) * 257)
    d = load_drive(root)
    assert [f.filename for f in d.frames] == [f"00000{i}{ext}" for i in range(3)]
    g = read_gray(d.frames[1])
    assert g.dtype == np.uint8 and g.shape == (d.camera.height, d.camera.width)


def test_empty_drive(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", n=0, gps=None)
    with pytest.raises(DriveFormatError, match="empty drive"):
        load_drive(root)
    with pytest.raises(DriveFormatError, match="drive folder not found"):
        load_drive(tmp_path / "nope")
    (tmp_path / "e").mkdir()
    (tmp_path / "e" / "camera.yaml").write_text(camera_yaml())
    with pytest.raises(DriveFormatError, match="frames/ folder is missing"):
        load_drive(tmp_path / "e")
    (tmp_path / "e" / "frames").mkdir()
    with pytest.raises(DriveFormatError, match="no .* images, and no frames.csv"):
        load_drive(tmp_path / "e")


def test_a_drive_without_frames_csv_or_gps_takes_the_images_in_name_order(
    tmp_path: Path,
) -> None:
    """A photo pair or series (two frames and camera.yaml, issue 29): sorted names, 1 / fps
    apart, with a warning; with a GPS log the times are needed to match it, so it is refused,
    naming the log."""
    root = make_drive(tmp_path / "d", n=3, gps=None)
    (root / "frames.csv").unlink()
    d = load_drive(root)
    assert [f.filename for f in d.frames] == sorted(f.filename for f in d.frames)
    assert np.allclose([f.timestamp_s for f in d.frames], np.arange(3) / d.camera.fps)
    assert any("frames.csv: not found" in w and "name order" in w for w in d.warnings)
    # numbers by value (a camera's unpadded IMG_2 ... IMG_10), hidden files left out
    series = make_drive(tmp_path / "s", n=0, gps=None)
    (series / "frames.csv").unlink()
    src = next((root / "frames").iterdir())
    for k in (1, 2, 10):
        (series / "frames" / f"IMG_{k}.png").write_bytes(src.read_bytes())
    (series / "frames" / "._IMG_3.png").write_bytes(b"not an image")
    d = load_drive(series)
    assert [f.filename for f in d.frames] == ["IMG_1.png", "IMG_2.png", "IMG_10.png"]
    with_gps = make_drive(tmp_path / "g", n=3)
    (with_gps / "frames.csv").unlink()
    with pytest.raises(DriveFormatError, match="frames.csv not found, and gps.csv needs"):
        load_drive(with_gps)


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_truncated_image_is_skipped_and_read_raises(tmp_path: Path, ext: str) -> None:
    root = make_drive(tmp_path / "d", ext=ext)
    p = root / "frames" / f"000002{ext}"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    d = load_drive(root)
    assert len(d.frames) == 4 and "000002" not in " ".join(f.filename for f in d.frames)
    (s,) = d.skipped
    assert s.file == f"frames/000002{ext}" and "truncated" in s.reason
    # The reader refuses the same file with FrameReadError (e.g. when check_images=False).
    d2 = load_drive(root, check_images=False)
    assert len(d2.frames) == 5
    with pytest.raises(FrameReadError, match="truncated"):
        read_image(d2.frames[2])
    with pytest.raises(FrameReadError):
        read_gray(d2.frames[2])


def test_garbage_image_is_skipped(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "frames" / "000001.png").write_bytes(b"not an image at all")
    (root / "frames" / "000003.png").write_bytes(b"")
    d = load_drive(root)
    assert len(d.frames) == 3
    reasons = {s.file: s.reason for s in d.skipped}
    assert "signature" in reasons["frames/000001.png"]
    assert "empty" in reasons["frames/000003.png"]


def test_corrupt_jpeg_body_with_valid_markers_is_skipped(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", ext=".jpg")
    p = root / "frames" / "000001.jpg"
    data = bytearray(p.read_bytes())
    # Keep SOI and EOI but destroy the headers: cv2 cannot decode it.
    data[2:200] = b"\x00" * 198
    p.write_bytes(bytes(data))
    d = load_drive(root)
    assert [s.file for s in d.skipped] == ["frames/000001.jpg"]


def test_image_size_mismatch_names_file(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    cv2.imwrite(str(root / "frames" / "000003.png"), np.zeros((H + 2, W, 3), np.uint8))
    with pytest.raises(DriveFormatError, match=r"000003.png: image is 64x50 px but camera.yaml"):
        load_drive(root)


def test_unlisted_images_warn(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    cv2.imwrite(str(root / "frames" / "zzz.png"), texture(1))
    d = load_drive(root)
    assert len(d.frames) == 5 and any("not listed" in w for w in d.warnings)


# --------------------------------------------------------------------------- speed


def test_check_images_is_fast_on_many_frames(tmp_path: Path) -> None:
    """Not a timing assertion: checks that 200 JPEG frames load and are all validated."""
    d = load_drive(make_drive(tmp_path / "d", n=200, ext=".jpg"))
    assert len(d.frames) == 200 and not d.skipped


def test_filename_too_long_for_the_file_system_is_a_missing_image(tmp_path: Path) -> None:
    """Found by tests/io/test_drive_fuzz.py: Path.is_file() raised ENAMETOOLONG."""
    root = make_drive(tmp_path / "d")
    rows = (root / "frames.csv").read_text().splitlines()
    rows[1] = "9" * 400 + rows[1]
    rows.insert(2, "frames/" + "8" * 400 + ".png,0.05")
    (root / "frames.csv").write_text("\n".join(rows) + "\n")
    d = load_drive(root)
    assert len(d.frames) == 4
    assert [s.line for s in d.skipped if s.file == "frames.csv"] == [2, 3]
