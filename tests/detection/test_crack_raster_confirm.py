"""A crack candidate confirmed on the surface raster (``crackraster.raster_crack_evidence``).

The rasters are the dense surface's kind of field: the true depth averaged over the matcher's
footprint and smoothed, times the share of the cross-section the matcher keeps, plus noise
correlated the way the dense surface's is (white noise through the same footprint and
smoothing: neighbouring cells correlate ~0.9 / 0.6 / 0.3 at 1 / 2 / 3 cells, as measured on the
nadir tilted drive). The null test counts confirmations on many seeded lines over crack-free
road: with a standard error that ignored the correlation (one profile per footprint taken as
independent) about a third of them would reach the threshold.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, uniform_filter

from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackraster import raster_crack_evidence
from tests.detection.synthetic import Scene, Trough
from tests.detection.test_crack_raster import ArraySource, _samples

CFG = CrackConfig()
GSD = 0.0037  # the dense raster's cell on the simulated drives (m)
FOOT = int(round(CFG.raster_footprint_cells))  # the footprint in cells (box)
SMOOTH = 1.5  # the dense surface's bilateral smoothing, 3 work px = 1.5 cells (σ, cells)
NOISE = 0.0004  # σ of a cell (m): 0.3-0.6 mm on the simulated drives


def _field(depth: np.ndarray, keep: float, seed: int) -> np.ndarray:
    """Residual (m, negative below): ``keep`` x the depth seen through the footprint and the
    smoothing, plus correlated noise of σ ``NOISE``."""
    rng = np.random.default_rng(seed)
    n = gaussian_filter(uniform_filter(rng.normal(size=depth.shape), FOOT), SMOOTH)
    n *= NOISE / n.std()
    return -keep * gaussian_filter(uniform_filter(depth, FOOT), SMOOTH) + n


def _grid(size_m: float) -> tuple[np.ndarray, np.ndarray]:
    k = int(round(size_m / GSD))
    y, x = np.mgrid[0:k, 0:k]
    return (x + 0.5) * GSD, size_m - (y + 0.5) * GSD


def _depth(scene: Scene, size_m: float, sub: int = 4) -> np.ndarray:
    """The scene's depth (m) averaged over each cell (``sub`` x ``sub`` samples per cell: a
    4 mm groove on 3.7 mm cells)."""
    k = int(round(size_m / GSD))
    y, x = np.mgrid[0 : k * sub, 0 : k * sub]
    d = scene.depth((x + 0.5) * GSD / sub, size_m - (y + 0.5) * GSD / sub)
    return d.reshape(k, sub, k, sub).mean(axis=(1, 3))


def test_crack_free_road_is_rarely_confirmed():
    """180 random straight lines (20-100 cm) over crack-free rasters: the one-sided level of
    raster_z_k = 3 (0.135 %) expects 0.24 confirmations; at most 2 pass, and the z values are
    centred (|mean| < 0.25) with a spread near the t distribution's (0.8-1.5)."""
    rng = np.random.default_rng(7)
    size = 1.6
    e, _ = _grid(size)
    zs, confirmed = [], 0
    for seed in range(6):
        src = ArraySource(_field(np.zeros_like(e), 1.0, seed), GSD)
        for _ in range(30):
            c = rng.uniform(0.55, size - 0.55, 2)
            length, a = rng.uniform(0.2, 1.0), rng.uniform(0.0, math.pi)
            t = np.linspace(-length / 2, length / 2, 300)
            xy = c + t[:, None] * np.array([math.cos(a), math.sin(a)])
            ev = raster_crack_evidence(src, xy + rng.normal(0, 0.001, xy.shape), 0.005, CFG)
            assert ev.blocks >= CFG.raster_min_blocks or not ev.confirmed
            if math.isfinite(ev.z):
                zs.append(ev.z)
            confirmed += ev.confirmed
    z = np.array(zs)
    assert len(z) > 150
    assert confirmed <= 2, confirmed
    assert abs(z.mean()) < 0.25, z.mean()
    assert 0.8 < z.std() < 1.5, z.std()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_crack_is_confirmed_on_the_raster(seed):
    """A 4 mm wide, 4.5 mm deep crack 70 cm long (D008 of the simulated drives) whose
    cross-section the raster keeps at 65 % (as at nadir): confirmed, its cross-section within
    4 standard errors of the kept ⅔ D w x 0.65 (the profiles' inner part holds the smoothed
    dip); the same line moved 8 cm aside is not confirmed."""
    t = Trough(0.3, 0.3, 0.9, 0.65, 0.004, 0.0045)
    src = ArraySource(_field(_depth(Scene(troughs=[t]), 1.2), 0.65, seed), GSD)
    xy = _samples(t, seed)
    ev = raster_crack_evidence(src, xy, 0.004, CFG)
    assert ev.confirmed, ev
    expect = 2.0 / 3.0 * 0.0045 * 0.004 * 0.65
    assert abs(ev.cross_section_m2 - expect) < 4 * ev.se_m2 + 0.2 * expect, (ev, expect)
    d = np.array([0.6, 0.35]) / np.hypot(0.6, 0.35)
    aside = raster_crack_evidence(src, xy + 0.08 * np.array([-d[1], d[0]]), 0.004, CFG)
    assert not aside.confirmed, aside


def test_short_or_sloped_candidates_are_not_confirmed():
    """A 12 cm candidate has too few blocks for its z; a 3 % cross-fall under a 60 cm candidate reads as
    no cross-section (each profile's road line takes the slope)."""
    t = Trough(0.3, 0.3, 0.9, 0.65, 0.004, 0.0045)
    e, n = _grid(1.2)
    src = ArraySource(_field(_depth(Scene(troughs=[t]), 1.2), 1.0, 4), GSD)
    short = Trough(0.5, 0.4, 0.6, 0.458, 0.004, 0.0045)
    ev = raster_crack_evidence(src, _samples(short, 4), 0.004, CFG)
    assert not ev.confirmed and ev.blocks <= 6, ev
    slope = ArraySource(_field(np.zeros_like(e), 1.0, 5) + 0.03 * (n - n.mean()), GSD)
    ev = raster_crack_evidence(slope, _samples(t, 5), 0.004, CFG)
    assert not ev.confirmed and abs(ev.z) < ev.threshold, ev


def test_no_raster_under_the_candidate():
    src = ArraySource(np.full((100, 100), np.nan), GSD)
    t = Trough(0.05, 0.05, 0.3, 0.3, 0.004, 0.0045)
    ev = raster_crack_evidence(src, _samples(t, 0), 0.004, CFG)
    assert not ev.confirmed and ev.blocks == 0
