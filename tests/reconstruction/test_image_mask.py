"""The camera's image mask (camera.yaml ``mask``, core.imagemask): a burned-in stamp that stays
fixed in the image matches itself with no motion; with the mask, features and dense heights
leave it out, and the road around it is measured as before."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from benchmarks.dense import RenderedPair, synthetic_pair
from roadsurf.core.imagemask import ImageMask
from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.config import FeatureConfig
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.parallax import dense_height

CFG = DenseHeightConfig(device="cpu")
BOX = (slice(10, 40), slice(20, 200))  # rows, cols of the stamp (inside the pair's overlap)


def _stamp(img: np.ndarray) -> np.ndarray:
    """A dashcam-like stamp: black box, white text, at the same pixels in every frame."""
    out = img.copy()
    out[BOX] = 0
    cv2.putText(out, "2026-11-28 12:00", (26, 32), cv2.FONT_HERSHEY_SIMPLEX, 0.6, 255, 2)
    return out


def _mask(shape: tuple[int, int]) -> ImageMask:
    usable = np.ones(shape, bool)
    usable[BOX] = False
    return ImageMask(cv2.erode(usable.astype(np.uint8), np.ones((5, 5))) > 0, "test")


@pytest.fixture(scope="module")
def pair() -> RenderedPair:
    return synthetic_pair((320, 240), seed=1)


def _heights(p: RenderedPair, stamped: bool, mask: ImageMask | None) -> tuple[np.ndarray, ...]:
    a, b = (_stamp(x) if stamped else x for x in (p.img_a, p.img_b))
    cam = dataclasses.replace(p.camera, mask=mask)
    dh = dense_height(a, b, cam, p.R, p.t, p.plane, cfg=CFG)
    return dh.height_m, dh.valid


def test_dense_leaves_the_masked_stamp_out(pair: RenderedPair) -> None:
    clean, clean_ok = _heights(pair, False, None)
    raw, raw_ok = _heights(pair, True, None)
    masked, masked_ok = _heights(pair, True, _mask(pair.img_a.shape))
    truth = pair.eta_true
    box = np.zeros(pair.img_a.shape, bool)
    box[BOX] = True
    # Without the mask the black box fails the exposure and correlation checks by itself
    # (no wrong height passes): the mask must not do worse than that, and must say so itself
    assert not (raw_ok & box & (np.abs(raw - truth) > 0.005)).any()
    # With it nothing in the box (nor within 2 px of it) is reported
    near = cv2.dilate(box.astype(np.uint8), np.ones((5, 5))) > 0
    assert not masked_ok[near].any()
    # ... and the road away from it reads as without the stamp (windows of 5 px, the sweep's
    # coarse grid and the smoothing reach ~12 px)
    far = ~(cv2.dilate(box.astype(np.uint8), np.ones((41, 41))) > 0)
    both = far & masked_ok & clean_ok
    assert both.sum() > 0.9 * (far & clean_ok).sum()
    assert np.nanmedian(np.abs(masked[both] - clean[both])) < 1e-4
    err_masked = np.abs(masked[masked_ok] - truth[masked_ok])
    assert np.mean(err_masked > 0.005) < 0.01


@pytest.mark.parametrize("scale", [1, 4])
def test_features_keep_off_the_mask(pair: RenderedPair, scale: int) -> None:
    """At 320 x 240 and at 1280 x 960 (above the detector's 0.3 Mpx cap: detected on a
    downscaled image, the mask test in full-resolution pixels)."""
    img = _stamp(pair.img_a)
    mask = _mask(img.shape)
    if scale > 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        mask = ImageMask(
            cv2.resize(mask.usable.astype(np.uint8), None, fx=scale, fy=scale,
                       interpolation=cv2.INTER_NEAREST) > 0
        )  # fmt: skip
    cfg = FeatureConfig()
    f_raw = feat.detect(img, cfg)
    f = feat.detect(img, cfg, mask)
    assert (~mask.usable_at(f_raw.keypoints_px)).sum() > 5  # the stamp's text has corners
    assert mask.usable_at(f.keypoints_px).all()
    # each keeps its own size (>= ~2 px) off the mask; the unmasked detector puts keypoints
    # right on its edge
    clear = mask.clearance_at(f.keypoints_px[:, 0], f.keypoints_px[:, 1])
    clear_raw = mask.clearance_at(f_raw.keypoints_px[:, 0], f_raw.keypoints_px[:, 1])
    assert clear.min() >= 2 and clear_raw.min() < 1
    assert len(f.keypoints_px) > 0.5 * len(f_raw.keypoints_px)


def test_a_changed_mask_changes_the_features_and_pairs_fingerprints(
    pair: RenderedPair, tmp_path
) -> None:
    from roadsurf.io.drive.types import Frame
    from roadsurf.reconstruction.config import ReconstructionConfig
    from roadsurf.reconstruction.stage import _feature_path, pair_fingerprint

    cfg = ReconstructionConfig()
    paths = [tmp_path / "a.png", tmp_path / "b.png"]
    for p, im in zip(paths, (pair.img_a, pair.img_b), strict=True):
        cv2.imwrite(str(p), im)
    a, b = (Frame(i, p.name, p, 0.1 * i) for i, p in enumerate(paths))
    m1 = _mask(pair.img_a.shape)
    u = m1.usable.copy()
    u[0, 0] = False
    m2 = ImageMask(u)
    cams = [pair.camera, dataclasses.replace(pair.camera, mask=m1),
            dataclasses.replace(pair.camera, mask=m2)]  # fmt: skip
    feats = {_feature_path(tmp_path, a, cfg, c.mask) for c in cams}
    pairs = {pair_fingerprint(cfg, c, a, b) for c in cams}
    assert len(feats) == 3 and len(pairs) == 3
    # and the same mask twice is the same work
    again = dataclasses.replace(pair.camera, mask=ImageMask(m1.usable))
    assert pair_fingerprint(cfg, again, a, b) == pair_fingerprint(cfg, cams[1], a, b)


def test_mask_digest_and_clearance() -> None:
    u = np.ones((20, 30), bool)
    u[5:8, 10:12] = False
    m = ImageMask(u)
    assert m == ImageMask(u.copy()) and hash(m) == hash(ImageMask(u.copy()))
    u2 = u.copy()
    u2[0, 0] = False
    assert m != ImageMask(u2)
    px = np.array([[10.0, 6.0], [10.0, 4.0], [10.0, 1.0], [-3.0, 2.0]])
    assert m.usable_at(px).tolist() == [False, True, True, True]
    # (10, 3) is 2 px from the masked block: usable with a margin of 1 px, not of 2 px
    q = np.array([[10.0, 3.0]])
    assert m.usable_at(q, 1.0)[0] and not m.usable_at(q, 2.0)[0]
    assert m.masked_share == pytest.approx(6 / 600)
