"""The real-photograph variants (benchmarks.real_photo_variants): each case is a drive whose
camera.yaml, images and labels agree (sizes, principal point, what moved with the pixels)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from benchmarks.real_photo_variants import CASES, _case
from roadsurf.io.drive import load_drive
from roadsurf.io.drive.staticpx import BLACK_DN

W, H = 160, 96


def _real(tmp: Path) -> Path:
    drive = tmp / "src" / "drive"
    (drive / "frames").mkdir(parents=True)
    (tmp / "src" / "labels").mkdir()
    rng = np.random.default_rng(0)
    rows = ["filename,timestamp_s"]
    for i in range(3):
        img = rng.integers(40, 220, (H, W, 3), dtype=np.uint8)
        cv2.imwrite(str(drive / "frames" / f"{i:06d}.jpg"), img)
        lab = np.zeros((H, W), np.uint8)
        lab[10:30, 100:140] = 255  # off-centre: a turn or a shift moves it
        cv2.imwrite(str(tmp / "src" / "labels" / f"{i:06d}.png"), lab)
        rows.append(f"{i:06d}.jpg,{0.5 * i}")
    (drive / "frames.csv").write_text("\n".join(rows) + "\n")
    cam = {"model": "pinhole", "width": W, "height": H, "fx": 150.0, "fy": 150.0,
           "cx": 79.5, "cy": 47.5, "dist": [0.0] * 5, "height_m": 0.5, "fps": 2.0}  # fmt: skip
    (drive / "camera.yaml").write_text(yaml.safe_dump(cam))
    return drive


@pytest.mark.parametrize("name", CASES)
def test_each_case_is_a_consistent_drive(tmp_path: Path, name: str) -> None:
    src = _real(tmp_path)
    drive = _case(name, src, tmp_path / name)
    d = load_drive(drive)
    cam = d.camera
    assert len(d.frames) == 3
    for f in d.frames:
        img = cv2.imread(str(f.path), cv2.IMREAD_UNCHANGED)
        lab = cv2.imread(str(drive.parent / "labels" / f"{f.path.stem}.png"), cv2.IMREAD_GRAYSCALE)
        assert img.shape[:2] == lab.shape == (cam.height, cam.width)
    img0 = cv2.imread(str(d.frames[0].path), cv2.IMREAD_UNCHANGED)
    lab0 = cv2.imread(str(drive.parent / "labels" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    if name in ("base", "height10"):  # the images untouched, byte for byte
        src0 = src / "frames" / "000000.jpg"
        assert d.frames[0].path.read_bytes() == src0.read_bytes()
    if name == "frame20":
        # black within JPEG's ringing (the 8 px blocks wholly inside the border)
        assert img0[:16].max() <= BLACK_DN and img0[:, -16:].max() <= BLACK_DN
    if name == "rot180":
        assert (cam.cx, cam.cy) == (W - 1 - 79.5, H - 1 - 47.5)
        assert lab0[H - 30 : H - 10, W - 140 : W - 100].min() == 255  # turned with the pixels
    if name == "crop":
        assert (cam.width, cam.height) == (W, H) and cam.cx == 79.5  # smaller than the crop
    if name == "half":
        assert (cam.width, cam.height, cam.fx) == (W // 2, H // 2, 75.0)
    if name == "height10":
        assert cam.height_m == pytest.approx(0.55)
    if name == "barrel":
        assert cam.dist[0] == -0.1 and img0[0, 0].max() <= BLACK_DN  # the corner left black
    if name == "grey":
        assert img0.ndim == 2
