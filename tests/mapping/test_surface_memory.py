"""mapping.surface: the local road fit's memory stays bounded by blocks, not by the drive's
length (issue 31 #10), with the same bits as the whole-drive gather."""

from __future__ import annotations

import tracemalloc

import numpy as np

from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.surface import LocalSurface, _window_sums


def test_window_sums_are_the_whole_gather_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    cell = np.concatenate([rng.normal(size=(9, 500)) * 1e3, np.zeros((9, 1))], axis=1)
    nb = rng.integers(-1, 500, size=(1234, 36))
    want = cell[:, nb].sum(axis=2)
    for block in (1, 7, 100, 5000):
        got = _window_sums(cell, nb, block)
        assert got.tobytes() == want.tobytes(), block


def test_local_fit_never_gathers_the_whole_corridor() -> None:
    """A 1.5 km, 3 m wide corridor of sparse points: the (9, nodes, 36) float64 gather of every
    node at once would be ~2.6 KB per node; the fit's traced peak stays well below that (it was 1.4x that before the blocks)."""
    rng = np.random.default_rng(0)
    n = 40_000
    xyz = np.c_[rng.uniform(0, 1500, n), rng.uniform(0, 3, n), rng.normal(0, 0.002, n)]
    cfg = MappingConfig()
    c = cfg.local_fit_cell_m
    cells = np.unique(np.floor(xyz[:, :2] / c).astype(np.int64), axis=0)
    corners = np.concatenate([cells + d for d in ([0, 0], [0, 1], [1, 0], [1, 1])])
    n_nodes = len(np.unique(corners, axis=0))
    h = max(1, int(round(0.5 * cfg.local_fit_window_m / c)))
    whole_gather = 9 * n_nodes * (2 * h) ** 2 * 8
    assert whole_gather > 100e6  # the case: a gather of the whole corridor would be large
    tracemalloc.start()
    try:
        surf = LocalSurface(cfg, xyz, progress=False)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(surf.node_keys) > 0.5 * n_nodes
    assert peak < 0.6 * whole_gather, (peak / 1e6, whole_gather / 1e6)
