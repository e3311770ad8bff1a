"""mapping.cloud.align_patches: the (N, 8) neighbour arrays are not duplicated (issue 31 #10:
memory flat in the drive's length; the raw points grow with it)."""

from __future__ import annotations

import tracemalloc

import numpy as np

from roadsurf.mapping.cloud import align_patches
from roadsurf.mapping.config import MappingConfig


def test_align_patches_keeps_one_copy_of_the_neighbour_arrays() -> None:
    """200k points in 0.5 m patches with height seams. Before, the distances, the indices, a
    masked copy of them and a masked copy of the neighbours' residuals were alive at once:
    traced peak 713 B per point (143 MB); now 540 B per point. Each (N, 8) float64 array is
    64 B per point, so the bound below sits between the two (two such arrays less)."""
    rng = np.random.default_rng(1)
    n = 200_000
    xyz = np.c_[rng.uniform(0, 400, n), rng.uniform(0, 3, n), rng.normal(0, 0.002, n)]
    patch = (xyz[:, 0] // 0.5).astype(np.int64) + rng.integers(0, 2, n)
    xyz[:, 2] += 0.001 * (patch % 3)  # seams of 1-2 mm between patches
    tracemalloc.start()
    try:
        out, stats = align_patches(MappingConfig(), xyz, patch)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert out.shape == xyz.shape and np.isfinite(out).all()
    assert stats  # offsets were applied
    assert peak / n < 713 - 1.5 * 64, peak / n
