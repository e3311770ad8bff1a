"""The dense matching's coarse-grid fallback (reconstruction.dense.pyramid,
DenseHeightConfig.fallback_levels): pixels that fail on the work grid take the height matched on
a grid coarser by 2.

The pair: benchmarks.dense.synthetic_pair (a 40 mm bowl in a textured flat road, nadir, exact
heights) whose pothole floor in image a carries its own fine grain (seeded noise, σ 30 DN, blur
0.7 px, against the road texture's 45 DN; clipped to 3-252 DN): the floor's fine detail differs between the views while
its coarser texture is shared, as on the real pothole floors of spd2 where a median 33 % of the
labelled pixels failed the ZNCC test at the work grid and a grid a quarter of the size kept
64 %."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from benchmarks.dense import RenderedPair, synthetic_pair
from roadsurf.reconstruction.dense.checks import (
    REJECT_EXPOSURE,
    REJECT_NCC,
    REJECT_OUTSIDE,
    REJECT_UNMATCHED,
)
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.geometry import PlaneParallax
from roadsurf.reconstruction.dense.parallax import DenseHeight, dense_height
from roadsurf.reconstruction.dense.pyramid import LevelMatch, fill_from_coarse, prior_on_grid

FLOOR_M = 0.02  # the floor: truth deeper than half the 40 mm bowl


@pytest.fixture(scope="module")
def grainy() -> RenderedPair:
    pair = synthetic_pair((320, 240), seed=3)
    floor = pair.depth_true > FLOOR_M
    n = cv2.GaussianBlur(
        np.random.default_rng(7).standard_normal(pair.img_a.shape).astype(np.float32), (0, 0), 0.7
    )
    n *= 30.0 / n.std()
    # kept within 3-252 DN: the floor is refused for its grain, not by the exposure test
    a = np.where(floor, np.clip(pair.img_a + n, 3, 252), pair.img_a)
    pair.img_a = a.astype(np.uint8)
    return pair


def _run(pair: RenderedPair, levels: int) -> DenseHeight:
    cfg = DenseHeightConfig(device="cpu", fallback_levels=levels)
    return dense_height(pair.img_a, pair.img_b, pair.camera, pair.R, pair.t, pair.plane, cfg=cfg)


@pytest.fixture(scope="module")
def runs(grainy: RenderedPair) -> tuple[DenseHeight, DenseHeight]:
    return _run(grainy, 0), _run(grainy, 1)


def test_fallback_measures_the_grainy_floor(
    grainy: RenderedPair, runs: tuple[DenseHeight, DenseHeight]
) -> None:
    off, on = runs
    assert on.level is not None
    floor = grainy.depth_true > FLOOR_M
    # measured: the work grid alone keeps 73 % of the floor, with the fallback 92 %; of its
    # deepest part (truth below 35 mm) 79 % and 93 %
    deep = grainy.depth_true > 0.035
    assert off.valid[floor].mean() < 0.8 and off.valid[deep].mean() < 0.85
    assert on.valid[floor].mean() > 0.88 and on.valid[deep].mean() > 0.88
    assert (on.level[floor] == 1).sum() > 0.12 * floor.sum()
    # the heights: no bias from the coarser windows (measured median error on the floor +0.2 mm,
    # on its deepest part -0.15 mm), so the deepest part reads at its depth
    err = on.height_m - grainy.eta_true
    assert abs(np.median(err[on.valid & floor])) < 1e-3
    assert abs(np.median(err[on.valid & deep])) < 1e-3


def test_fallback_variance_is_honest(
    grainy: RenderedPair, runs: tuple[DenseHeight, DenseHeight]
) -> None:
    """The filled pixels carry the coarse match's larger variance, widened by the relief in
    its window (a bound: conservative on the floor), and their errors stay within it (the
    median |z| of a normal error is 0.674; measured 0.58 at level 0, 0.37 at level 1; σ on the
    floor 2.6 against 10 mm)."""
    _, on = runs
    assert on.level is not None
    e = on.height_m - grainy.eta_true
    z = np.abs(e) / np.sqrt(on.var_m2)
    assert 0.4 < np.median(z[on.level == 0]) < 1.0
    assert 0.15 < np.median(z[on.level == 1]) < 0.8
    assert np.percentile(z[on.level == 1], 90) < 2.0
    floor = grainy.depth_true > FLOOR_M
    sd0 = np.median(np.sqrt(on.var_m2[(on.level == 0) & floor]))
    sd1 = np.median(np.sqrt(on.var_m2[(on.level == 1) & floor]))
    assert sd1 > 1.3 * sd0


def test_fill_variance_spans_the_relief_in_the_window() -> None:
    """A fill next to a 20 mm coarse step, its four neighbours all on one side: with 5 x 5
    windows the step is within reach and (10 mm)² is added; with 1 x 1 windows nothing."""
    hc, wc = 10, 12
    hts = np.where(np.arange(wc)[None, :] < 6, 0.0, -0.02) * np.ones((hc, 1))
    coarse = _level(hc, wc, hts, np.ones((hc, wc), bool), 0.5)
    K = np.array([[300.0, 0, 12], [0, 300.0, 10], [0, 0, 1]])
    pp = PlaneParallax.from_pair(np.eye(3), np.array([0.0, -0.3, 0.0]), np.array([0, 0, 1.1]), K)
    for win, extra in ((1, 0.0), (5, 0.01**2)):
        fine = LevelMatch.empty(2 * hc, 2 * wc, 1.0)
        fill_from_coarse(fine, coarse, pp, 0.5, win)
        # fine column 7 reads coarse columns 3 and 4 (both 0 m); column 6 is 2 coarse px away
        np.testing.assert_allclose(fine.height_m[5, 7], 0.0, atol=1e-9)
        np.testing.assert_allclose(fine.var_m2[5, 7], 1e-6 + extra, rtol=1e-5)
        # far from the step (columns 0-1 read coarse columns 0 and 1): never widened
        np.testing.assert_allclose(fine.var_m2[5, 1], 1e-6, rtol=1e-5)


def test_fallback_leaves_the_work_grid_alone(runs: tuple[DenseHeight, DenseHeight]) -> None:
    off, on = runs
    assert off.level is not None and on.level is not None
    assert set(np.unique(off.level)) <= {-1, 0}
    np.testing.assert_array_equal(on.level == 0, off.valid)
    np.testing.assert_array_equal(on.height_m[off.valid], off.height_m[off.valid])
    assert np.array_equal(on.valid, on.level >= 0)
    # a filled pixel's parallax is its height's on the work grid
    m = on.level == 1
    u, v = on.work_px()
    s = on.model.shift_from_height(on.height_m[m].astype(float), u[m], v[m])
    np.testing.assert_allclose(on.shift_px[m], s, atol=1e-3)


def _level(h: int, w: int, heights: np.ndarray, valid: np.ndarray, scale: float) -> LevelMatch:
    lv = LevelMatch.empty(h, w, scale)
    lv.valid[:] = valid
    lv.height_m[:] = np.where(valid, heights, np.nan)
    lv.var_m2[:] = np.where(valid, 1e-6, np.nan)
    lv.ncc[:] = np.where(valid, 0.9, np.nan)
    return lv


def test_fill_needs_four_valid_neighbours_and_adds_the_spread() -> None:
    """A coarse step of 20 mm: fine pixels between the two sides get the interpolated height
    with (10 mm)² added to the variance; next to a coarse hole nothing is filled."""
    hc, wc = 10, 12
    hts = np.where(np.arange(wc)[None, :] < 6, 0.0, -0.02) * np.ones((hc, 1))
    valid = np.ones((hc, wc), bool)
    valid[4, 2] = False  # a coarse hole
    coarse = _level(hc, wc, hts, valid, 0.5)
    fine = LevelMatch.empty(2 * hc, 2 * wc, 1.0)
    K = np.array([[300.0, 0, 12], [0, 300.0, 10], [0, 0, 1]])
    pp = PlaneParallax.from_pair(np.eye(3), np.array([0.0, -0.3, 0.0]), np.array([0, 0, 1.1]), K)
    filled = fill_from_coarse(fine, coarse, pp, 0.5)
    assert filled.sum() > 0.8 * filled.size
    assert np.array_equal(filled, fine.valid)
    # fine pixel u has coarse coordinate 0.5 (u + 0.5) - 0.5: columns 10..13 straddle 5 | 6
    np.testing.assert_allclose(fine.height_m[0, 11], -0.02 * 0.25, atol=1e-7)
    np.testing.assert_allclose(fine.var_m2[0, 11], 1e-6 + 0.01**2, rtol=1e-5)
    np.testing.assert_allclose(fine.var_m2[0, 2], 1e-6, rtol=1e-5)
    # the fine pixels whose bilinear neighbours include the coarse hole (4, 2) stay empty
    assert not fine.valid[7:11, 3:7].any()
    # a valid fine pixel is never overwritten
    fine2 = LevelMatch.empty(2 * hc, 2 * wc, 1.0)
    fine2.valid[0, 0], fine2.height_m[0, 0] = True, 0.005
    fill_from_coarse(fine2, coarse, pp, 0.5)
    assert fine2.height_m[0, 0] == np.float32(0.005)


def test_prior_on_grid_reads_the_finer_field() -> None:
    """A height field linear in the finer grid's u, v read at a coarser crop's pixels."""
    h, w = 40, 60
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    field = 1e-3 * u - 2e-3 * v
    got = prior_on_grid(field, 0.5, 3, 4, 10, 12)
    vc, uc = np.mgrid[0:10, 0:12].astype(float)
    uf, vf = (uc + 4 + 0.5) / 0.5 - 0.5, (vc + 3 + 0.5) / 0.5 - 0.5
    np.testing.assert_allclose(got, 1e-3 * uf - 2e-3 * vf, atol=1e-6)


def test_reject_flags_name_the_check(
    grainy: RenderedPair, runs: tuple[DenseHeight, DenseHeight]
) -> None:
    """Each refused pixel says which check refused it (dense.checks): the grainy floor the
    ZNCC test (measured: 76 % of the refused floor pixels carry the bit), a saturated patch the
    exposure test, pixels that image b does not see are not matched."""
    off, on = runs
    assert off.reject is not None and on.reject is not None
    np.testing.assert_array_equal(off.valid, off.reject == 0)
    np.testing.assert_array_equal(on.reject, off.reject)  # filled pixels keep their flags
    floor = grainy.depth_true > FLOOR_M
    refused = floor & ~off.valid
    assert ((off.reject[refused] & REJECT_NCC) != 0).mean() > 0.6
    assert (off.reject[~floor & off.valid] == 0).all()
    u, v = off.work_px()
    q = np.stack([u, v, np.ones_like(u)], -1) @ off.model.H.T
    x = q[..., 0] / q[..., 2]
    unseen = (x < -20) | (x > grainy.camera.width + 20)
    if unseen.any():
        assert ((off.reject[unseen] & (REJECT_UNMATCHED | REJECT_OUTSIDE)) != 0).all()
    a = grainy.img_a.copy()
    a[100:120, 40:70] = 255
    cfg = DenseHeightConfig(device="cpu", fallback_levels=0)
    dh = dense_height(a, grainy.img_b, grainy.camera, grainy.R, grainy.t, grainy.plane, cfg=cfg)
    assert dh.reject is not None
    assert ((dh.reject[102:118, 42:68] & REJECT_EXPOSURE) != 0).all()
    assert not dh.valid[100:120, 40:70].any()
