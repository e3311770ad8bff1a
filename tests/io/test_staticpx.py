"""Pixels that never change over a drive (io.drive.staticpx): a burned-in stamp with or without
its box, the bonnet, over-exposed sky; not a fine-grained low-contrast road, not a stop."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from roadsurf.io.drive.staticpx import MIN_REGION_SHARE, static_pixels
from roadsurf.io.drive.types import Frame

W, H = 1280, 720  # above the 640 px work width: the σ map is downscaled
BORDER = 20  # px of black round every frame (border=True)


def _road(rng: np.random.Generator, contrast: float, grain_px: int) -> np.ndarray:
    """A stretch of road: blurred noise of the given contrast (DN σ) and grain."""
    n = rng.normal(0.0, 1.0, (H // grain_px + 1, W // grain_px + 1)).astype(np.float32)
    n = cv2.resize(n, (W, H), interpolation=cv2.INTER_LINEAR)
    return np.clip(120 + contrast * n / max(float(n.std()), 1e-6), 0, 255).astype(np.uint8)


def _text(img: np.ndarray, k: int, org: tuple[int, int], outline: bool) -> None:
    txt = f"2026-11-28 12:00:{k:02d} 48 km/h"
    if outline:  # white letters with a black outline straight on the road (no box)
        cv2.putText(img, txt, org, cv2.FONT_HERSHEY_SIMPLEX, 1.0, 0, 6, cv2.LINE_AA)
    cv2.putText(img, txt, org, cv2.FONT_HERSHEY_SIMPLEX, 1.0, 255, 2, cv2.LINE_AA)


def _drive(tmp: Path, n: int = 12, **kind: bool) -> tuple[list[Frame], np.ndarray]:
    """Frames of a moving camera with the overlays asked for; the truth of the static pixels."""
    rng = np.random.default_rng(5)
    truth = np.zeros((H, W), bool)
    frames = []
    for k in range(n):
        img = _road(rng, 6.0 if kind.get("fine") else 25.0, 1 if kind.get("fine") else 3)
        if kind.get("box"):
            img[20:70, 20:520] = 0
            _text(img, k, (30, 58), False)
            truth[20:70, 20:520] = True
        if kind.get("text"):
            _text(img, k, (700, 680), True)
        if kind.get("sky"):
            img[:100] = 255
            truth[:100] = True
        if kind.get("stop"):
            img = _road(np.random.default_rng(1), 25.0, 3)
        if kind.get("border"):  # a letterbox / undistortion border: black, JPEG-noisy
            ring = np.ones((H, W), bool)
            ring[BORDER:-BORDER, BORDER:-BORDER] = False
            img[ring] = rng.integers(0, 6, int(ring.sum()))
            truth |= ring
        p = tmp / f"f{k:02d}.png"
        cv2.imwrite(str(p), img)
        frames.append(Frame(k, p.name, p, 0.1 * k))
    if kind.get("text"):  # the part that does not change: date and time of day, outlined
        probe = np.zeros((H, W), np.uint8)
        cv2.putText(probe, "2026-11-28 12:00:", (700, 680), cv2.FONT_HERSHEY_SIMPLEX, 1.0, 255, 6)
        truth |= probe > 0
    return frames, truth


def test_a_stamp_in_a_box_is_found_and_the_suggestion_covers_it(tmp_path: Path) -> None:
    frames, truth = _drive(tmp_path, box=True)
    sp = static_pixels(frames, W, H)
    assert sp is not None
    assert sp.static[truth].mean() > 0.95
    assert sp.static[~truth].mean() < 0.005
    suggestion = sp.suggested_mask()
    assert (suggestion[truth] == 0).all()  # grown by the work grid's pixel + 3
    assert "burned-in stamp" in sp.warning("m.png")


def test_a_text_stamp_without_a_box_is_found(tmp_path: Path) -> None:
    """White letters outlined in black straight on the road: the date and time-of-day part is
    the same in every frame (the seconds change)."""
    frames, truth = _drive(tmp_path, text=True)
    sp = static_pixels(frames, W, H)
    assert sp is not None and sp.share >= MIN_REGION_SHARE
    ys, xs = np.nonzero(sp.static)
    assert 640 < xs.min() and ys.min() > 600  # where the stamp is, nowhere else
    assert (sp.suggested_mask()[truth] == 0).mean() > 0.9


def test_sky_is_named_as_over_exposure(tmp_path: Path) -> None:
    frames, _ = _drive(tmp_path, sky=True)
    sp = static_pixels(frames, W, H)
    assert sp is not None and sp.share == pytest.approx(100 / H, abs=0.01)
    assert "over-exposed" in sp.warning("m.png")


def test_fine_low_contrast_road_and_a_stop_are_not_static(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    frames, _ = _drive(tmp_path / "a", fine=True)
    sp = static_pixels(frames, W, H)
    assert sp is None or sp.share == 0
    frames, _ = _drive(tmp_path / "b", stop=True)  # the same road in every frame: cannot tell
    assert static_pixels(frames, W, H) is None


def test_too_few_or_unreadable_frames_say_nothing(tmp_path: Path) -> None:
    frames, _ = _drive(tmp_path, n=5, box=True)
    assert static_pixels(frames, W, H) is None
    frames, _ = _drive(tmp_path, n=8, box=True)
    for f in frames[:3]:
        f.path.write_bytes(b"junk")
    assert static_pixels(frames, W, H) is None


def test_a_photo_pair_s_black_border_is_found_from_two_frames(tmp_path: Path) -> None:
    """Two frames cannot tell a stamp from the road, but a black border they can: a photo
    pair from an undistorted camera has it masked too (no pixel called static)."""
    frames, truth = _drive(tmp_path, n=2, border=True, box=True)
    sp = static_pixels(frames, W, H)
    assert sp is not None and not sp.static.any()
    ring = np.ones((H, W), bool)
    ring[BORDER:-BORDER, BORDER:-BORDER] = False
    assert sp.black_border[ring].mean() > 0.99 and not sp.black_border[~truth].any()


def test_a_black_border_is_its_own_not_a_static_ring_round_everything(tmp_path: Path) -> None:
    """A black frame round every image (letterbox, undistortion): found as the black border,
    left out of the static pixels; it used to close into a ring whose filled inside made the
    whole image 'static' (100 %, a suggested mask hiding everything). A stamp inside still is."""
    frames, truth = _drive(tmp_path, border=True, box=True)
    sp = static_pixels(frames, W, H)
    assert sp is not None
    ring = np.ones((H, W), bool)
    ring[BORDER:-BORDER, BORDER:-BORDER] = False
    assert sp.black_border[ring].mean() > 0.99 and not sp.black_border[~truth].any()
    # the stamp's black box touches the border and joins it; its text is static
    assert (sp.static | sp.black_border)[truth].mean() > 0.95
    assert sp.static[~truth].mean() < 0.005 and sp.share < 0.05


def test_a_border_the_mask_names_is_not_judged(tmp_path: Path) -> None:
    """With camera.yaml's mask naming the border, the static test looks inside it only (it
    reported 90 % with the mask's edge closed into a ring on the work grid)."""
    frames, _ = _drive(tmp_path, border=True)
    usable = np.zeros((H, W), bool)
    usable[BORDER:-BORDER, BORDER:-BORDER] = True
    sp = static_pixels(frames, W, H, usable)
    assert sp is not None and sp.share < 0.005 and not sp.black_border.any()


def test_the_pipeline_masks_a_black_border(tmp_path: Path) -> None:
    from roadsurf.core.camera import Camera
    from roadsurf.io.drive.types import Drive
    from roadsurf.pipeline.run_checks import static_pixels as check

    frames, truth = _drive(tmp_path, border=True)
    cam = Camera(W, H, 900.0, 900.0, W / 2, H / 2, 1.5, 10.0)
    drive = Drive(tmp_path, cam, frames, None, None)
    assert check(drive, tmp_path) is None  # nothing else static: no suggestion
    assert drive.camera.mask is not None
    assert (~drive.camera.mask.usable == truth).mean() > 0.99
    (w,) = drive.warnings
    assert "black in every frame along its edges" in w
    assert not (tmp_path / "suggested_mask.png").exists()


def test_a_stamp_beside_an_auto_masked_border_is_not_said_outside_a_mask(tmp_path: Path) -> None:
    """camera.yaml has no mask: the stamp's warning must not speak of one (the border's own
    mask is the run's, not the user's)."""
    from roadsurf.core.camera import Camera
    from roadsurf.io.drive.types import Drive
    from roadsurf.pipeline.run_checks import static_pixels as check

    frames, _ = _drive(tmp_path, border=True, text=True)
    drive = Drive(tmp_path, Camera(W, H, 900.0, 900.0, W / 2, H / 2, 1.5, 10.0), frames, None, None)
    msg = check(drive, tmp_path)
    assert msg is not None and "outside camera.yaml's mask" not in msg
    assert (tmp_path / "suggested_mask.png").exists() and len(drive.warnings) == 2
