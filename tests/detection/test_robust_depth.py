"""The reported max depth is a supported maximum: one outlier point or cell cannot set it, and
a real small pothole's bottom is not eroded (``roadsurf.detection.robust``)."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import Point

from roadsurf.detection.config import MapSegmentConfig
from roadsurf.detection.dense import combine_dense
from roadsurf.detection.densepair import PairDense
from roadsurf.detection.mapseg import Region, measure
from roadsurf.detection.measurement import pair_max_depth, point_max_depth
from roadsurf.detection.robust import supported_max
from roadsurf.io.formats import GridSpec

MC = MapSegmentConfig()
# (depth m, radius m): the pothole (18.6 mm) and a real small one (30 mm, 8 cm wide)
POTHOLES = [(0.0186, 0.15), (0.030, 0.04)]


def _bowl(xy: np.ndarray, depth: float, radius: float) -> np.ndarray:
    """Depth (m, positive down) of a bowl pothole centred at the origin."""
    r2 = (xy**2).sum(axis=1) / radius**2
    return depth * np.clip(1.0 - r2, 0.0, None)


def _points(depth: float, radius: float, spacing: float, seed: int, noise: float = 0.0003):
    """Points on a jittered grid over the pothole and its road ring: grid xy, depth."""
    rng = np.random.default_rng(seed)
    g = np.arange(-radius - 0.25, radius + 0.25, spacing)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = xy + rng.uniform(-0.3, 0.3, xy.shape) * spacing
    return xy, _bowl(xy, depth, radius) + rng.normal(0, noise, len(xy))


def _inject_outlier(xy: np.ndarray, d: np.ndarray, depth: float) -> np.ndarray:
    """One point near the bottom read 10 cm deeper than the pothole."""
    d = d.copy()
    d[np.argmin((xy**2).sum(axis=1))] = depth + 0.10
    return d


@pytest.mark.parametrize("outlier", [False, True])
@pytest.mark.parametrize(("depth", "radius"), POTHOLES)
def test_pair_max_depth_ignores_one_outlier_and_keeps_the_bottom(depth, radius, outlier):
    xy, d = _points(depth, radius, 0.006, seed=1)
    if outlier:
        d = _inject_outlier(xy, d, depth)
    cam = np.c_[xy, 1.0 + d]  # camera-a frame looking down: deeper is further (z larger)
    got = pair_max_depth(Point(0, 0).buffer(radius), [(xy, cam)], MC)
    assert got is not None
    assert abs(got - depth) < 0.0015


@pytest.mark.parametrize("outlier", [False, True])
@pytest.mark.parametrize(("depth", "radius"), POTHOLES)
def test_map_point_max_depth_ignores_one_outlier_and_keeps_the_bottom(depth, radius, outlier):
    xy, d = _points(depth, radius, 0.006, seed=2)
    if outlier:
        d = _inject_outlier(xy, d, depth)
    got = point_max_depth(Point(0, 0).buffer(radius), xy, -d, MC)
    assert got is not None
    assert abs(got - depth) < 0.0015


def test_map_point_max_depth_ignores_two_scattered_outliers():
    depth, radius = POTHOLES[0]
    xy, d = _points(depth, radius, 0.006, seed=3)
    d = _inject_outlier(xy, d, depth)
    d[np.argsort((xy**2).sum(axis=1))[5]] = depth + 0.05  # a second, different mismatch
    got = point_max_depth(Point(0, 0).buffer(radius), xy, -d, MC)
    assert got is not None
    assert abs(got - depth) < 0.0015


@pytest.mark.parametrize("outlier", [False, True])
@pytest.mark.parametrize(("depth", "radius"), POTHOLES)
def test_raster_max_depth_ignores_one_outlier_cell_and_keeps_the_bottom(depth, radius, outlier):
    gsd = 0.005
    grid = GridSpec("EPSG:32617", -0.5, 0.5, gsd, 200, 200)
    rr, cc = np.meshgrid(np.arange(200), np.arange(200), indexing="ij")
    xy = grid.xy_from_rowcol(rr.ravel(), cc.ravel())
    dep = _bowl(xy, depth, radius)
    ins = dep > 0
    rows, cols, d = rr.ravel()[ins], cc.ravel()[ins], dep[ins]
    if outlier:
        d = d.copy()
        d[np.argmax(d)] = depth + 0.10  # one cell filled from a mismatched point
    reg = Region(rows=rows, cols=cols, depth_m=d, depth_smooth_m=d)
    got = measure(reg, grid, 0.01).max_depth_m
    assert abs(got - depth) < 0.0015


@pytest.mark.parametrize("outlier", [False, True])
@pytest.mark.parametrize(("depth", "radius"), POTHOLES)
def test_dense_max_depth_ignores_outlier_tracks_and_keeps_the_bottom(depth, radius, outlier):
    spacing = 0.003
    xy, d = _points(depth, radius, spacing, seed=4, noise=0.0002)
    if outlier:
        # failed tracks: one at the bottom 10 cm deeper, and a few more around it
        d = _inject_outlier(xy, d, depth)
        near = np.argsort((xy**2).sum(axis=1))
        d[near[[20, 60, 120]]] += np.array([0.05, 0.08, 0.12])
    got = combine_dense(
        Point(0, 0).buffer(radius),
        [PairDense(xy_m=xy, depth_m=d, spacing_m=spacing, noise_m=0.0002)],
        edge_m=0.03, rim_k=2.0, rim_floor_m=0.002,
    )  # fmt: skip
    assert got is not None
    assert abs(got.max_depth_m - depth) < 0.002


def test_supported_max_rules():
    v = np.array([0.02, 0.0195, 0.019, 0.12, np.nan])
    assert supported_max(v, 2) == pytest.approx(0.02)
    assert supported_max(v, 3) == pytest.approx(0.02)
    # no value has the support: the k-th deepest
    assert supported_max(np.array([0.3, 0.2, 0.1]), 2) == pytest.approx(0.2)
    # fewer than k values: the shallowest; none: None
    assert supported_max(np.array([0.03, 0.01]), 3) == pytest.approx(0.01)
    assert supported_max(np.array([np.nan]), 2) is None


def test_dense_band_of_failed_tracks_in_one_of_two_pairs_does_not_set_the_max():
    """The fault campaign's case: two pairs see an 18.6 mm pothole; one pair's tracks fail in
    a band across the bottom (10 cm deeper). The median over two pairs is their mean, which
    read 107.7 mm; the reading the other pair does not support is dropped."""
    depth, radius, spacing = 0.0186, 0.15, 0.003
    xy, d = _points(depth, radius, spacing, seed=5, noise=0.0002)
    xy2, d2 = _points(depth, radius, spacing, seed=6, noise=0.0002)
    band = (np.abs(xy2[:, 1]) < 0.025) & (np.abs(xy2[:, 0]) < 0.14)
    d2 = d2 + np.where(band, 0.10, 0.0)
    got = combine_dense(
        Point(0, 0).buffer(radius),
        [
            PairDense(xy_m=xy, depth_m=d, spacing_m=spacing, noise_m=0.0002),
            PairDense(xy_m=xy2, depth_m=d2, spacing_m=spacing, noise_m=0.0002),
        ],
        edge_m=0.03, rim_k=2.0, rim_floor_m=0.002,
    )  # fmt: skip
    assert got is not None
    assert abs(got.max_depth_m - depth) < 0.0015


def test_region_is_judged_by_its_unsmoothed_supported_max_not_the_smoothed_one():
    """The thresholds' smoothing shaves the bottom of a pothole a few times its σ wide: a real
    11 x 7 cm pothole read 8.6 mm smoothed (< min_depth_m, 10 mm) and was dropped as shallow
    before it was measured. It is judged by the statistic it is measured by: the unsmoothed
    raster's supported max (12 mm here)."""
    from roadsurf.detection.config import DetectionConfig
    from roadsurf.detection.mapseg import Segmentation, raster_max_depth
    from roadsurf.detection.measurement import measure_regions

    gsd = 0.005
    grid = GridSpec("EPSG:32617", -0.5, 0.5, gsd, 200, 200)
    rr, cc = np.meshgrid(np.arange(200), np.arange(200), indexing="ij")
    xy = grid.xy_from_rowcol(rr.ravel(), cc.ravel())
    r = np.linalg.norm(xy, axis=1)
    raw = 0.012 * np.clip((0.06 - r) / 0.02, 0.0, 1.0)  # flat 12 mm floor, 2 cm walls
    ins = raw > 0
    smooth = np.minimum(raw[ins], 0.009)  # the smoothing shaved the floor to 9 mm
    reg = Region(rows=rr.ravel()[ins], cols=cc.ravel()[ins], depth_m=raw[ins],
                 depth_smooth_m=smooth, noise_m=0.001, seed_m=0.008)  # fmt: skip
    assert raster_max_depth(reg) == pytest.approx(0.012)
    seg = Segmentation(0.001, 0.008, 0.0015, [reg], grid)
    defects, _ = measure_regions(DetectionConfig(), seg, {}, have_pairs=False)
    assert len(defects) == 1
    assert defects[0].max_depth_m == pytest.approx(0.012)
