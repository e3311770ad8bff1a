"""Seam steps: the height disagreement between neighbouring pairs' patches where both measured
the road, per seam the median difference and its standard error.

Two sources, the denser first:

- ``dense_seams.npz`` (a run with the dense surface, ``mapping.dense_seams``): each pair's own
  levelled height in every cell (on a sub-grid one matching window apart) that two pairs
  measured, i.e. the samples the surface is fused from. Thousands of samples per seam.
- ``map_points.npz`` (any run): the sparse feature points of patch k and the next one within
  1.5 cm of each other. A few hundred per seam: each median's standard error is 0.2-0.4 mm.

Flat road only: samples with |residual| < 1 cm on both sides (a pothole wall's misplacement is
the trajectory's error, not a seam). The standard error of a median is 1.2533 x the samples'
σ / √n (σ = 1.4826 MAD); ``noise_floor_m`` is the expected largest |step| of seams that are
pure noise with those errors (seeded Monte Carlo): a maximum at the floor says nothing about
the seams, one well above it is a real step.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.io import runfolder as rf

FLAT_M = 0.01  # |residual| below this on both sides: flat road (m)
MIN_SAMPLES = 20  # fewer common samples: no seam measured
SPARSE_RADIUS_M = 0.015  # a sparse point's partner within this (m)
MEDIAN_SE = math.sqrt(math.pi / 2)  # a median's standard error over the mean's (normal samples)


def _median_se(diff: np.ndarray) -> float:
    mad = MAD_TO_SIGMA * float(np.median(np.abs(diff - np.median(diff))))
    return MEDIAN_SE * mad / math.sqrt(len(diff))


def seam_table(run_dir: Path) -> tuple[str, np.ndarray]:
    """(source, rows): source ``dense``, ``sparse`` or ``none``; rows (S, 5) per seam: frame a
    of the first patch, of the second, step (second minus first, m), its standard error (m) and
    the number of samples."""
    dense = run_dir / rf.DENSE_SEAMS
    if dense.is_file():
        with np.load(dense, allow_pickle=False) as z:
            rows = _dense_seams(z["row"], z["col"], z["frame_index"], z["residual_m"])
        if len(rows):
            return "dense", rows
    path = run_dir / rf.MAP_POINTS
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            rows = _sparse_seams(z["xyz"], z["residual_m"].astype(float), z["frame_index"])
        return "sparse", rows
    return "none", np.zeros((0, 5))


def _dense_seams(
    row: np.ndarray, col: np.ndarray, frame: np.ndarray, resid: np.ndarray
) -> np.ndarray:
    """Per consecutive pair of patches: the common cells' height differences."""
    out = []
    key = row.astype(np.int64) * (int(col.max(initial=0)) + 1) + col.astype(np.int64)
    ids = np.unique(frame)
    for a, b in zip(ids[:-1], ids[1:], strict=True):
        A, B = frame == a, frame == b
        common, ia, ib = np.intersect1d(key[A], key[B], return_indices=True)
        ra, rb = resid[A][ia].astype(float), resid[B][ib].astype(float)
        ok = (np.abs(ra) < FLAT_M) & (np.abs(rb) < FLAT_M)
        if ok.sum() < MIN_SAMPLES:
            continue
        d = rb[ok] - ra[ok]
        out.append((a, b, float(np.median(d)), _median_se(d), len(d)))
    return np.array(out, float).reshape(-1, 5)


def _sparse_seams(xyz: np.ndarray, resid: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Per consecutive pair of patches: nearby points' residual differences."""
    from scipy.spatial import cKDTree

    flat = np.abs(resid) < FLAT_M
    xyz, resid, frame = xyz[flat], resid[flat], frame[flat]
    ids = np.unique(frame)
    out = []
    for a, b in zip(ids[:-1], ids[1:], strict=True):
        A, B = frame == a, frame == b
        if A.sum() < MIN_SAMPLES or B.sum() < MIN_SAMPLES:
            continue
        tree = cKDTree(xyz[A, :2])
        d, j = tree.query(xyz[B, :2], distance_upper_bound=SPARSE_RADIUS_M)
        ok = np.isfinite(d)
        if ok.sum() < MIN_SAMPLES:
            continue
        diff = resid[B][ok] - resid[A][j[ok]]
        out.append((a, b, float(np.median(diff)), _median_se(diff), len(diff)))
    return np.array(out, float).reshape(-1, 5)


def noise_floor_m(se: np.ndarray, draws: int = 4000, seed: int = 0) -> float:
    """Expected largest |step| over seams whose steps are N(0, se²) noise (m)."""
    if len(se) == 0:
        return float("nan")
    z = np.random.default_rng(seed).standard_normal((draws, len(se)))
    return float(np.mean(np.max(np.abs(z * se), axis=1)))


def seam_report(run_dir: Path) -> dict[str, Any]:
    """The seam figures of a run folder: largest and 95th-percentile |step| (m), the seams'
    count, source, median standard error, the noise floor and the largest |step| / error."""
    source, t = seam_table(Path(run_dir))
    if len(t) == 0:
        return {"seam_step_max_m": float("nan"), "seam_step_p95_m": float("nan"),
                "seam_pairs": 0, "seam_source": source}  # fmt: skip
    s, se = np.abs(t[:, 2]), t[:, 3]
    return {
        "seam_step_max_m": float(s.max()),
        "seam_step_p95_m": float(np.percentile(s, 95)),
        "seam_pairs": len(s),
        "seam_source": source,
        "seam_step_se_median_m": float(np.median(se)),
        "seam_noise_floor_m": noise_floor_m(se),
        "seam_step_max_z": float(np.max(s / np.maximum(se, 1e-9))),
        "seam_samples_median": float(np.median(t[:, 4])),
    }


def seam_steps(run_dir: Path) -> tuple[float, float, int]:
    """Largest and 95th-percentile |seam step| (m) and the number of seams (``seam_report``)."""
    r = seam_report(run_dir)
    return r["seam_step_max_m"], r["seam_step_p95_m"], r["seam_pairs"]
