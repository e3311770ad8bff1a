"""Dense two-view height (reconstruction.dense.parallax) on seeded synthetic pairs with an exact
height field (benchmarks.dense.synthetic_pair: a 40 mm pothole in a textured flat road, nadir
and tilted 30°): heights, sub-pixel precision, the variance, and the pixels it must refuse."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from benchmarks.dense import RenderedPair, score, synthetic_pair
from roadsurf.core.errors import RoadsurfError
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.parallax import DenseHeight, dense_height

CFG = DenseHeightConfig(device="cpu")


def _run(pair: RenderedPair, cfg: DenseHeightConfig = CFG, **kw: object) -> DenseHeight:
    a = kw.pop("img_a", pair.img_a)
    b = kw.pop("img_b", pair.img_b)
    return dense_height(a, b, pair.camera, pair.R, pair.t, pair.plane, cfg=cfg)  # type: ignore[arg-type]


def _overlap(pair: RenderedPair, dh: DenseHeight) -> np.ndarray:
    """Pixels of a whose road point lies inside image b with a margin of 4 px."""
    u, v = dh.ideal_px()
    q = np.stack([u, v, np.ones_like(u)], -1) @ dh.model.H.T  # scale 1: model.H is a -> b
    x, y = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
    w, h = pair.camera.width, pair.camera.height
    m = 4
    inb = (x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)
    return inb & (u >= m) & (u <= w - 1 - m) & (v >= m) & (v <= h - 1 - m)


@pytest.fixture(scope="module")
def nadir() -> RenderedPair:
    return synthetic_pair((320, 240), seed=1)


@pytest.fixture(scope="module")
def nadir_dense(nadir: RenderedPair) -> DenseHeight:
    return _run(nadir)


def test_nadir_pothole_heights(nadir: RenderedPair, nadir_dense: DenseHeight) -> None:
    sc = score(nadir_dense, nadir, cfg_window=CFG.window_px)
    # measured: flat 0.72 mm, pothole 1.09 mm, 0.076 px (320 x 240, 2 DN noise)
    assert sc["flat_mae_mm"] < 1.0
    assert sc["pothole_mae_mm"] < 1.6
    assert sc["shift_mad_px"] < 0.1  # sub-pixel precision on textured road
    assert abs(sc["shift_bias_px"]) < 0.02
    assert sc["coverage_pothole"] > 0.85
    ov = _overlap(nadir, nadir_dense)
    # nearly every pixel of the overlap (measured 97.1%; the rest: pothole walls, the texture's
    # few black spots)
    assert nadir_dense.valid[ov].mean() > 0.95
    assert not nadir_dense.valid[~_overlap_loose(nadir, nadir_dense)].any()
    # the deepest point: within 3 mm of the 40 mm pothole
    deepest = np.nanpercentile(nadir_dense.height_m, 0.05)
    assert deepest == pytest.approx(-0.04, abs=0.003)


def _overlap_loose(pair: RenderedPair, dh: DenseHeight) -> np.ndarray:
    u, v = dh.ideal_px()
    q = np.stack([u, v, np.ones_like(u)], -1) @ dh.model.H.T
    x, y = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
    w, h = pair.camera.width, pair.camera.height
    m = -6  # parallax of the relief can reach a few px past the road's overlap
    return (x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)


def test_variance_matches_the_errors(nadir: RenderedPair, nadir_dense: DenseHeight) -> None:
    # median |error| / σ is 0.67 for Gaussian errors with the right σ (measured 0.59)
    assert 0.4 < score(nadir_dense, nadir)["z_median"] < 1.0
    v = nadir_dense.var_m2[nadir_dense.valid]
    assert np.all(v > 0) and np.median(np.sqrt(v)) < 0.003


def test_points_lie_on_the_surface(nadir: RenderedPair, nadir_dense: DenseHeight) -> None:
    X, var = nadir_dense.points_cam_a()
    assert len(X) == nadir_dense.valid.sum() and len(var) == len(X)
    n = np.array([-nadir.plane[0], -nadir.plane[1], 1.0])
    d = nadir.plane[2] / np.linalg.norm(n)
    n /= np.linalg.norm(n)
    assert np.allclose(d - X @ n, nadir_dense.height_m[nadir_dense.valid], atol=1e-6)


def test_tilted_camera_30deg() -> None:
    pair = synthetic_pair((320, 240), pitch_deg=30.0, seed=2)
    dh = _run(pair)
    sc = score(dh, pair)
    # measured: flat 1.42 mm (far pixels see 2x larger ground cells), pothole 2.17 mm
    assert sc["flat_mae_mm"] < 2.0
    assert sc["pothole_mae_mm"] < 3.0
    assert sc["shift_mad_px"] < 0.12
    assert sc["coverage_pothole"] > 0.8


def test_dis_init_agrees_with_the_sweep(nadir: RenderedPair, nadir_dense: DenseHeight) -> None:
    dh = _run(nadir, dataclasses.replace(CFG, init="dis"))
    both = dh.valid & nadir_dense.valid
    assert both.sum() > 0.95 * nadir_dense.valid.sum()
    assert np.median(np.abs(dh.height_m[both] - nadir_dense.height_m[both])) < 1e-4


def test_refuses_textureless_saturated_and_mismatched_pixels(nadir: RenderedPair) -> None:
    a, b = nadir.img_a.copy(), nadir.img_b.copy()
    a[20:60, 20:80] = 128  # textureless
    a[80:120, 20:80] = 255  # saturated
    rng = np.random.default_rng(9)
    b[130:180, 200:260] = rng.integers(40, 200, (50, 60))  # a moving object: only b has it
    dh = _run(nadir, img_a=a, img_b=b)
    assert dh.valid[26:54, 26:74].mean() < 0.02
    assert dh.valid[86:114, 26:74].mean() < 0.02
    # a's pixels whose road point b sees on the object (H⁻¹ of its rectangle, inset 6 px)
    q = np.array([[206, 136, 1.0], [253, 173, 1.0]]) @ np.linalg.inv(dh.model.H).T
    (c0, r0), (c1, r1) = np.round(q[:, :2] / q[:, 2:]).astype(int)
    assert 10 < r1 - r0 and dh.valid[r0:r1, c0:c1].mean() < 0.05
    # the rest of the overlap is still measured
    rest = _overlap(nadir, dh)
    rest[14:126, 14:86] = False
    rest[r0 - 12 : r1 + 12, c0 - 12 : c1 + 12] = False
    assert dh.valid[rest].mean() > 0.95


def test_scale_half_gives_a_quarter_of_the_pixels(nadir: RenderedPair) -> None:
    dh = _run(nadir, dataclasses.replace(CFG, scale=0.5))
    assert dh.shape == (120, 160)
    sc = score(dh, nadir)
    assert sc["pothole_mae_mm"] < 3.0 and sc["coverage_pothole"] > 0.8


def test_wrong_image_size_is_an_error(nadir: RenderedPair) -> None:
    with pytest.raises(RoadsurfError, match="uint8 grey image"):
        _run(nadir, img_a=nadir.img_a[:-1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_gives_the_cpu_heights(nadir: RenderedPair, nadir_dense: DenseHeight) -> None:
    dh = _run(nadir, dataclasses.replace(CFG, device="cuda"))
    both = dh.valid & nadir_dense.valid
    assert both.sum() > 0.99 * nadir_dense.valid.sum()
    assert np.abs(dh.height_m[both] - nadir_dense.height_m[both]).max() < 2e-4


def test_a_pothole_deeper_than_the_search_is_matched_again_deeper() -> None:
    """A 200 mm pothole against the default 120 mm search: its floor reaches the bound over a
    patch, and the pair is matched again down to 240 mm (max_depth_limit_m); without the
    second search the floor is cut at the bound."""
    pair = synthetic_pair((320, 240), seed=3, pothole_depth_m=0.2, pothole_radius_m=0.25)
    deep = _run(pair)
    floor = pair.eta_true < -0.17  # the truth's floor, 50 mm past the first search
    assert floor.sum() > 200
    got = deep.height_m[floor & deep.valid]
    assert got.size > 0.5 * floor.sum()
    assert np.median(got) == pytest.approx(np.median(pair.eta_true[floor & deep.valid]), abs=0.005)
    once = _run(pair, dataclasses.replace(CFG, max_depth_limit_m=CFG.max_depth_m))
    cut = once.height_m[floor & once.valid]
    assert cut.size == 0 or float(np.nanmin(cut)) > -0.135
