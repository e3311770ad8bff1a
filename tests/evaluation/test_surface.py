"""The imaged corridor of the surface evaluation: true camera footprints from camera.yaml."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.evaluation.surface import _corridor_polygon


def _drive(tmp_path: Path, dist: list[float]) -> Path:
    (tmp_path / "truth").mkdir()
    (tmp_path / "camera.yaml").write_text(
        "model: pinhole\nwidth: 640\nheight: 480\nfx: 600.0\nfy: 600.0\ncx: 319.5\ncy: 239.5\n"
        f"dist: {dist}\nheight_m: 1.1\nfps: 15.0\n"
    )
    return tmp_path / "truth"


def _nadir_truth() -> dict[str, object]:
    # one camera looking straight down (180° about x: camera z -> world -z), at the origin
    return {"filename": ["a.png"], "xy": np.zeros((1, 2)), "q": np.array([[0.0, 1.0, 0.0, 0.0]])}


def test_corridor_of_an_ideal_camera_is_its_pixel_centre_rectangle(tmp_path: Path) -> None:
    poly = _corridor_polygon(_drive(tmp_path, [0.0] * 5), _nadir_truth(), {"a.png"})
    assert poly is not None
    assert poly.area == pytest.approx((639 / 600 * 1.1) * (479 / 600 * 1.1), rel=1e-12)


def test_corridor_follows_the_lens_distortion(tmp_path: Path) -> None:
    # barrel distortion: the raw image's corners see further out than an ideal camera's
    poly = _corridor_polygon(
        _drive(tmp_path, [-0.12, 0.03, 0.0, 0.0, 0.0]), _nadir_truth(), {"a.png"}
    )
    assert poly is not None
    assert poly.area > 1.05 * (639 / 600 * 1.1) * (479 / 600 * 1.1)


def test_no_camera_yaml_no_corridor(tmp_path: Path) -> None:
    (tmp_path / "truth").mkdir()
    assert _corridor_polygon(tmp_path / "truth", _nadir_truth(), {"a.png"}) is None


def test_two_view_corridor_pairs_consecutive_frames_after_a_skyward_frame(tmp_path: Path) -> None:
    """Frames a, b (nadir, far apart), c (looking up: no footprint), d, e (nadir, overlapping).
    The two-view corridor is d∩e only; a shifted list would also intersect b with d."""
    up = [1.0, 0.0, 0.0, 0.0]  # identity: camera z points up, its rays miss the road
    down = [0.0, 1.0, 0.0, 0.0]
    truth = {
        "filename": ["a", "b", "c", "d", "e"],
        "xy": np.array([[0.0, 0.0], [5.0, 0.0], [9.0, 0.0], [5.2, 0.0], [5.4, 0.0]]),
        "q": np.array([down, down, up, down, down]),
    }
    seen = {"a", "b", "c", "d", "e"}
    poly = _corridor_polygon(_drive(tmp_path, [0.0] * 5), truth, seen, stereo=True)
    assert poly is not None
    w, h = 639 / 600 * 1.1, 479 / 600 * 1.1
    assert poly.area == pytest.approx((w - 0.2) * h, rel=1e-9)
