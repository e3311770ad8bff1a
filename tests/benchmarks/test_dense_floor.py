"""benchmarks.dense_floor's per-pair figures on a hand-made height map: shares of the labelled
pixels measured, filled and refused first by each check."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from benchmarks.dense_floor import pair_figures
from roadsurf.reconstruction.dense.checks import (
    REJECT_LR,
    REJECT_NCC,
    REJECT_STEP,
    REJECT_TEXTURE,
    REJECT_UNMATCHED,
)


def test_pair_figures_count_each_pixel_once() -> None:
    h, w = 10, 10
    reject = np.zeros((h, w), np.uint8)
    level = np.zeros((h, w), np.int8)
    reject[0, :] = REJECT_UNMATCHED  # not matched: not counted
    reject[1, :5] = REJECT_NCC | REJECT_STEP  # counts as ncc (first in the order)
    reject[1, 5:] = REJECT_TEXTURE
    reject[2, :] = REJECT_LR
    level[0:3, :] = -1
    level[1, :5] = 1  # filled from the coarser grid
    valid = level >= 0
    height = np.where(valid, -0.02, np.nan).astype(np.float32)
    dh = SimpleNamespace(shape=(h, w), reject=reject, level=level, valid=valid, height_m=height)
    label = np.zeros((20, 20), bool)
    label[:10, :] = True  # rows 0-4 of the work grid
    f = pair_figures(dh, label)
    assert f is not None
    assert f["labelled_px"] == 40  # rows 1-4 (row 0 unmatched)
    np.testing.assert_allclose(f["valid"], 25 / 40)
    np.testing.assert_allclose(f["valid_work_grid"], 20 / 40)
    np.testing.assert_allclose(f["valid_filled"], 5 / 40)
    np.testing.assert_allclose(f["first_ncc"], 5 / 40)
    np.testing.assert_allclose(f["first_texture"], 5 / 40)
    np.testing.assert_allclose(f["first_lr"], 10 / 40)
    assert f["first_step"] == 0.0
    np.testing.assert_allclose(f["road_valid"], 1.0)
    np.testing.assert_allclose(f["height_p2_mm"], -20.0, atol=1e-4)
