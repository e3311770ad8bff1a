"""Seeds from the dense surface's measured deep cells (detection.rasterseeds): a pothole the map
measured opens a window even where the pairs left no deep sparse point; fills, cells whose own
σ is large and single cells do not."""

from __future__ import annotations

import numpy as np

from roadsurf.detection.config import MapSegmentConfig
from roadsurf.detection.rasterseeds import raster_seeds
from roadsurf.io.formats import GridSpec

GSD = 0.004


class _Source:
    def __init__(self, res: np.ndarray, count: np.ndarray | None, sigma: np.ndarray) -> None:
        self.res, self.count, self.sigma = res, count, sigma
        h, w = res.shape
        self.grid = GridSpec("local ENU", 0.0, h * GSD, GSD, w, h)

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        return self.res[r0 : r0 + h, c0 : c0 + w]

    def read_count(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        return None if self.count is None else self.count[r0 : r0 + h, c0 : c0 + w]

    def read_sigma(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        return self.sigma[r0 : r0 + h, c0 : c0 + w]


def test_measured_pothole_seeds_a_window_fills_and_noise_do_not() -> None:
    rng = np.random.default_rng(1)
    res = rng.normal(0.0, 0.0005, (600, 1500)).astype(np.float32)
    count = np.ones(res.shape, np.uint8)
    sigma = np.full(res.shape, 0.001, np.float32)
    yy, xx = np.mgrid[0:600, 0:1500]
    pit = (
        np.hypot(yy - 300, xx - 1024) < 25
    )  # 20 cm across (50 cells of 4 mm), 30 mm deep, cut by a block edge
    res[pit] = -0.03
    fill = np.hypot(yy - 300, xx - 300) < 25  # as deep, but filled (count 0)
    res[fill], count[fill] = -0.03, 0
    vague = np.hypot(yy - 300, xx - 700) < 25  # as deep, but its cells' σ is 2 cm
    res[vague], sigma[vague] = -0.03, 0.02
    res[100, 100] = -0.05  # one cell
    seeds = raster_seeds(_Source(res, count, sigma), MapSegmentConfig())
    assert len(seeds) >= 1
    centre = _Source(res, count, sigma).grid.xy_from_rowcol(np.array([300.0]), np.array([1024.0]))
    assert np.all(np.linalg.norm(seeds - centre, axis=1) < 0.1), seeds
    # a sparse surface (no counts): nothing, its cells are interpolations
    assert len(raster_seeds(_Source(res, None, sigma), MapSegmentConfig())) == 0
