"""Seam steps of `roadsurf evaluate` (``evaluation.seams``): the dense surface's per-pair samples
first, the sparse map points as fallback; a 1 mm seam is found, a seamless drive passes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.evaluation.seams import noise_floor_m, seam_report, seam_steps, seam_table
from roadsurf.io.formats import GridSpec
from roadsurf.mapping.dense_seams import DENSE_SEAMS, SeamSamples, seam_stride_cells

SIGMA_M = 0.0015  # per-sample height noise of a dense cell (the drives' flat MAE ~1 mm)


def _dense_run(
    tmp_path: Path, offsets_m: list[float], seed: int = 0, pothole: bool = False
) -> Path:
    """Six pairs along a 2 m strip, each measuring 0.8 m of it on 5 mm cells (every 2nd kept),
    consecutive pairs overlapping by 0.4 m: 3200 common cells kept per seam."""
    rng = np.random.default_rng(seed)
    grid = GridSpec("EPSG:32617", 0.0, 0.0, 0.005, 2000, 200)
    ss = SeamSamples(grid, stride=2)
    width = 200 * 5
    rows, cols = np.mgrid[0:160, 0:width]
    truth = np.zeros(rows.shape)
    if pothole:  # 4 cm deep across the second seam: not flat road, left out
        truth[40:120, 440:520] = -0.04
    samples = []
    for k, off in enumerate(offsets_m):
        sel = (cols >= 80 * k) & (cols < 80 * k + 160)
        cell = (rows[sel] * width + cols[sel]).astype(np.int64)
        val = truth[sel] + off + rng.normal(0, SIGMA_M, sel.sum())
        samples.append((10 + k, cell, val))
    ss.add(0, 0, width, samples)
    ss.write(tmp_path / DENSE_SEAMS)
    return tmp_path


def test_a_1mm_seam_in_the_dense_samples_is_found(tmp_path: Path) -> None:
    run = _dense_run(tmp_path, [0, 0, 0, 0.001, 0, 0])
    rep = seam_report(run)
    assert rep["seam_source"] == "dense" and rep["seam_pairs"] == 5
    # (2, 3) steps up 1 mm, (3, 4) down: each measured within 5 standard errors
    source, t = seam_table(run)
    assert t[2, 2] == pytest.approx(0.001, abs=5 * t[2, 3])
    assert t[3, 2] == pytest.approx(-0.001, abs=5 * t[3, 3])
    assert rep["seam_step_max_m"] > 0.0008
    assert rep["seam_step_max_m"] > 3 * rep["seam_noise_floor_m"]  # far above the noise
    # 1.2533 x 1.5 mm x √2 / √3200 = 0.047 mm a seam
    assert rep["seam_step_se_median_m"] == pytest.approx(0.047e-3, rel=0.15)


def test_a_seamless_dense_drive_passes_at_its_noise_floor(tmp_path: Path) -> None:
    run = _dense_run(tmp_path, [0.0] * 6, seed=1)
    rep = seam_report(run)
    assert rep["seam_source"] == "dense"
    assert rep["seam_step_max_m"] < 0.5e-3  # issue 30's target
    assert rep["seam_step_max_m"] < 3 * rep["seam_noise_floor_m"]
    mx, p95, n = seam_steps(run)
    assert (mx, n) == (rep["seam_step_max_m"], 5) and p95 <= mx


def test_a_pothole_across_a_seam_is_not_a_step(tmp_path: Path) -> None:
    # the pothole's cells are left out as not flat; both pairs see it alike anyway
    run = _dense_run(tmp_path, [0.0] * 6, seed=2, pothole=True)
    assert seam_report(run)["seam_step_max_m"] < 0.5e-3


def _sparse_points(tmp_path: Path, offsets_m: list[float], seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    xyz, r, fr = [], [], []
    for k, off in enumerate(offsets_m):
        p = np.column_stack([rng.uniform(0.4 * k, 0.4 * k + 0.8, 1500), rng.uniform(0, 1, 1500)])
        xyz.append(np.column_stack([p, np.zeros(len(p))]))
        r.append(off + rng.normal(0, SIGMA_M, len(p)))
        fr.append(np.full(len(p), k))
    np.savez(
        tmp_path / "map_points.npz",
        xyz=np.concatenate(xyz),
        residual_m=np.concatenate(r).astype(np.float32),
        frame_index=np.concatenate(fr),
    )
    return tmp_path


def test_sparse_fallback_finds_the_seam_with_a_larger_error(tmp_path: Path) -> None:
    run = _sparse_points(tmp_path, [0, 0, 0.001, 0])
    rep = seam_report(run)
    assert rep["seam_source"] == "sparse" and rep["seam_pairs"] == 3
    assert rep["seam_step_max_m"] > 0.0006
    # a few hundred pairs of points within 1.5 cm: an error several times the dense one
    assert 0.1e-3 < rep["seam_step_se_median_m"] < 0.3e-3


def test_dense_samples_come_first(tmp_path: Path) -> None:
    _sparse_points(tmp_path, [0, 0.002, 0])  # a sparse seam the dense samples do not have
    _dense_run(tmp_path, [0.0] * 6, seed=3)
    rep = seam_report(tmp_path)
    assert rep["seam_source"] == "dense" and rep["seam_step_max_m"] < 0.5e-3


def test_no_points_no_seams(tmp_path: Path) -> None:
    rep = seam_report(tmp_path)
    assert rep["seam_pairs"] == 0 and rep["seam_source"] == "none"
    assert np.isnan(rep["seam_step_max_m"])


def test_noise_floor_of_pure_noise() -> None:
    # the largest of 50 |N(0, 1)| (as of 100 N(0, 1)): 2.51 on average (order statistics)
    assert noise_floor_m(np.full(50, 1.0)) == pytest.approx(2.51, abs=0.05)


def test_seam_samples_keep_cells_two_pairs_saw_on_the_sub_grid(tmp_path: Path) -> None:
    ss = SeamSamples(GridSpec("EPSG:32617", 0.0, 0.0, 0.005, 100, 100), stride=3)
    cells_a, cells_b = np.arange(0, 60), np.arange(30, 90)  # row 0 of a 100-wide tile
    ss.add(6, 0, 100, [(1, cells_a, np.zeros(60)), (2, cells_b, np.ones(60))])
    z = np.load(ss.write(tmp_path / "s.npz"))
    assert set(z["col"].tolist()) == set(range(30, 60, 3))  # common cells, every 3rd column
    assert (z["row"] == 6).all() and len(z["row"]) == 20
    assert float(z["gsd_m"]) == 0.005 and int(z["stride"]) == 3
    # one matching window (5 px) over 2 px cells: every 3rd cell
    assert seam_stride_cells(5, 2.0) == 3 and seam_stride_cells(5, 0.0) == 1
