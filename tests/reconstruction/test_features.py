"""Feature detection options: even spread over weak (low-contrast) regions, border padding,
CLAHE, and the detection-resolution cap."""

from __future__ import annotations

import numpy as np

from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.config import FeatureConfig
from tests.reconstruction.conftest import texture


def _half_faint(seed: int = 3) -> np.ndarray:
    """Texture whose right half has 1/8 of the contrast (a cast shadow on asphalt)."""
    img = texture((384, 512), seed).astype(np.float64)
    img[:, 256:] = 100 + (img[:, 256:] - img[:, 256:].mean()) / 8
    return np.clip(img, 0, 255).astype(np.uint8)


def _share_right(f: feat.Features) -> float:
    return float(np.mean(f.keypoints_px[:, 0] >= 256))


def test_grid_spread_fills_low_contrast_half() -> None:
    img = _half_faint()
    plain = feat.detect(img, FeatureConfig(max_features=600, grid_cells=0))
    spread = feat.detect(img, FeatureConfig(max_features=600, grid_cells=16))
    strict = feat.detect(img, FeatureConfig(max_features=600, contrast_threshold=0.04))
    # OpenCV's default threshold finds (almost) nothing in the faint half, grid or not.
    assert _share_right(strict) < 0.1
    assert len(spread.keypoints_px) == 600
    # Strongest-first puts nearly everything in the bright half; the grid quota does not.
    assert _share_right(spread) > _share_right(plain) + 0.1
    assert _share_right(spread) > 0.3


def test_border_pad_and_clahe_keep_keypoints_inside_the_image() -> None:
    img = _half_faint()
    cfg = FeatureConfig(max_features=800, grid_cells=16, border_pad_px=16, clahe_clip=2.0)
    f = feat.detect(img, cfg)
    assert len(f.keypoints_px) > 400
    assert f.descriptors.shape == (len(f.keypoints_px), 128)
    assert f.keypoints_px.min() >= 0
    assert f.keypoints_px[:, 0].max() <= 511 and f.keypoints_px[:, 1].max() <= 383


def test_detection_cap_returns_full_resolution_pixels() -> None:
    img = texture((384, 512), 5)
    f_full = feat.detect(img, FeatureConfig(max_features=500, max_detect_megapixels=0))
    f_half = feat.detect(img, FeatureConfig(max_features=500, max_detect_megapixels=0.05))
    # Both in the full image's pixel frame: the downscaled keypoints match the full-resolution ones.
    ia, ib = feat.match(f_full, f_half, FeatureConfig())
    assert len(ia) > 50
    err = np.linalg.norm(f_full.keypoints_px[ia] - f_half.keypoints_px[ib], axis=1)
    assert np.median(err) < 1.0


def test_feature_cache_round_trips_bit_for_bit_and_stores_sift_as_bytes(tmp_path) -> None:
    """SIFT descriptors (float32 holding whole numbers 0-255) are stored as uint8, losslessly
    and uncompressed; other descriptors as they are. Older zlib files with float descriptors
    still load."""
    from roadsurf.core.atomic import write_npz_atomic

    sift = feat.detect(texture((240, 320), 5), FeatureConfig(max_features=300))
    assert sift.descriptors.dtype == np.float32 and len(sift.descriptors) > 50
    rng = np.random.default_rng(0)
    frac = feat.Features(sift.keypoints_px, sift.descriptors + 0.25, "sift")  # not whole
    binary = feat.Features(
        sift.keypoints_px, rng.integers(0, 256, (len(sift.descriptors), 32), np.uint8), "orb"
    )
    for f, stored in ((sift, np.uint8), (frac, np.float32), (binary, np.uint8)):
        path = feat.save_features(tmp_path / f"{f.kind}{stored.__name__}.npz", f)
        with np.load(path) as z:
            assert z["descriptors"].dtype == stored
        back = feat.load_features(path)
        assert back.descriptors.dtype == f.descriptors.dtype and back.kind == f.kind
        assert np.array_equal(back.descriptors, f.descriptors)
        assert np.array_equal(back.keypoints_px, f.keypoints_px)
    # a cache file of the earlier layout (zlib, float32 descriptors, no dtype entry)
    old = write_npz_atomic(
        tmp_path / "old.npz", keypoints_px=sift.keypoints_px, descriptors=sift.descriptors,
        kind=np.asarray("sift"),
    )  # fmt: skip
    assert np.array_equal(feat.load_features(old).descriptors, sift.descriptors)
