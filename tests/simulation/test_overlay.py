"""Image-fixed overlays in the simulator (simulation.overlay): the burned-in stamp box and the
hood stay on the same pixels while the road moves, the image mask marks them, camera.yaml
names it only with write_mask, and the defaults change nothing. The drives are read file by
file (cv2, yaml), not through the drive loader."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from roadsurf.core.errors import ConfigError
from roadsurf.simulation.overlay import overlay_pixels, text_box_px
from roadsurf.simulation.scenarios import make_config, simulate

SMALL: dict[str, Any] = {"width": 192, "height": 144, "fx": 180.0, "image_format": "png"}
OVERLAYS: dict[str, Any] = {"overlay_text": True, "hood_share": 0.2}
SEED = 11


def _drive(root: Path, name: str, **kw: Any) -> Path:
    return simulate("potholes", root / name, seed=SEED, n_frames=2, progress=False, **SMALL, **kw)


def _frames(out: Path) -> list[np.ndarray]:
    return [_read(p) for p in sorted((out / "frames").iterdir())]


def _read(path: Path) -> np.ndarray:
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert m is not None, path
    return m


@pytest.fixture(scope="module")
def drives(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("overlay")
    return {
        "plain": _drive(root, "plain"),
        "masked": _drive(root, "masked", write_mask=True, **OVERLAYS),
        "unmasked": _drive(root, "unmasked", **OVERLAYS),
    }


def test_stamp_box_stays_put_while_its_text_and_the_road_change(drives: dict[str, Path]) -> None:
    a, b = _frames(drives["masked"])
    x0, y0, x1, y1 = text_box_px(SMALL["width"], SMALL["height"])
    assert y1 - y0 >= 12
    outline = np.zeros(a.shape[:2], bool)
    outline[y0:y1, x0:x1] = True
    outline[y0 + 1 : y1 - 1, x0 + 1 : x1 - 1] = False  # the box's border ring (no text there)
    assert np.array_equal(a[outline], b[outline])
    assert a[outline].max() == 0  # opaque black
    inner = (slice(y0, y1), slice(x0, x1))
    assert a[inner].max() > 200  # white (anti-aliased) text
    assert not np.array_equal(a[inner], b[inner])  # the time changes per frame
    road = ~cv2.dilate(overlay_pixels(make_config("potholes", **SMALL, **OVERLAYS)).astype(
        np.uint8), np.ones((5, 5), np.uint8)).astype(bool)  # fmt: skip
    diff = np.abs(a.astype(int) - b.astype(int))[road]
    assert diff.mean() > 5.0  # the road moved under the camera
    ring = np.zeros(a.shape[:2], bool)  # just outside the box: road, not black
    ring[y1 + 1, x0:x1] = True
    assert a[ring].mean() > 30


def test_hood_pixels_are_identical_across_frames(drives: dict[str, Path]) -> None:
    cfg = make_config("potholes", **SMALL, hood_share=0.2)
    hood = overlay_pixels(cfg)
    a, b = _frames(drives["masked"])
    assert hood[-1].all() and not hood[: int(0.75 * SMALL["height"])].any()
    # the edge is highest at the centre: more hood rows in the middle column than at the side
    assert hood[:, SMALL["width"] // 2].sum() > hood[:, 0].sum() >= 0.6 * 0.2 * SMALL["height"]
    assert np.array_equal(a[hood], b[hood])
    assert a[hood].mean() < 80  # dark paint
    assert a[hood].std() > 1.0  # shaded, not flat


def test_overlay_only_changes_its_own_pixels(drives: dict[str, Path]) -> None:
    """The overlay is drawn after the sensor model: every other pixel is the plain render's,
    and the truth rasters and files are the same."""
    cfg = make_config("potholes", **SMALL, **OVERLAYS)
    covered = overlay_pixels(cfg)
    for a, p in zip(_frames(drives["masked"]), _frames(drives["plain"]), strict=True):
        assert np.array_equal(a[~covered], p[~covered])
        assert not np.array_equal(a[covered], p[covered])
    for name in ("height.tif", "residual.tif", "defects.geojson", "poses.csv"):
        plain = (drives["plain"] / "truth" / name).read_bytes()
        assert (drives["masked"] / "truth" / name).read_bytes() == plain, name


def test_mask_marks_the_overlay_and_camera_yaml_names_it(drives: dict[str, Path]) -> None:
    out = drives["masked"]
    cam = yaml.safe_load((out / "camera.yaml").read_text())
    assert cam["mask"] == "mask.png"
    m = _read(out / cam["mask"])
    assert m.dtype == np.uint8 and m.shape == (cam["height"], cam["width"])
    assert set(np.unique(m)) == {0, 255}
    covered = overlay_pixels(make_config("potholes", **SMALL, **OVERLAYS))
    assert (m[covered] == 0).all()  # 0 on every overlay pixel
    grown = cv2.dilate(covered.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.array_equal(m == 0, grown)  # and exactly 2 px around it, no more
    assert np.array_equal(_read(out / "truth" / "mask.png"), m)


def test_truth_mask_without_write_mask_and_no_mask_by_default(drives: dict[str, Path]) -> None:
    out = drives["unmasked"]
    assert "mask" not in yaml.safe_load((out / "camera.yaml").read_text())
    assert not (out / "mask.png").exists()
    assert np.array_equal(_read(out / "truth" / "mask.png"), _read(drives["masked"] / "mask.png"))
    plain = drives["plain"]
    assert "mask" not in yaml.safe_load((plain / "camera.yaml").read_text())
    assert not (plain / "mask.png").exists() and not (plain / "truth" / "mask.png").exists()


def test_rerender_over_a_masked_drive_and_hood_share_range(tmp_path: Path) -> None:
    out = _drive(tmp_path, "d", write_mask=True, hood_share=0.1)
    assert (out / "mask.png").exists()
    _drive(tmp_path, "d")  # a simulated drive's mask.png is replaced with the rest of it
    assert not (out / "mask.png").exists() and not (out / "truth" / "mask.png").exists()
    with pytest.raises(ConfigError, match="hood_share"):
        make_config("potholes", hood_share=0.6)


def test_greyscale_frames_get_the_overlay(tmp_path: Path) -> None:
    out = _drive(tmp_path, "g", greyscale=True, **OVERLAYS)
    a, b = _frames(out)
    assert a.ndim == 2
    x0, y0, x1, y1 = text_box_px(SMALL["width"], SMALL["height"])
    assert a[y0, x0:x1].max() == 0 and a[y0:y1, x0:x1].max() > 200
    hood = overlay_pixels(make_config("potholes", **SMALL, hood_share=0.2, greyscale=True))
    assert np.array_equal(a[hood], b[hood])
