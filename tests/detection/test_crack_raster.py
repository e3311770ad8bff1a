"""Cracks measured across their centre line on the surface raster (detection.crackraster), and a
3 mm crack next to a 40 mm pothole detected on a rendered drive (issue 29: "cracks >= 3 mm wide
and >= 3 mm deep: detected, with length within 20 %").

The rasters are known height fields seen the way the dense surface sees them: the true depth
box-averaged over the matcher's footprint (``raster_footprint_cells`` cells), plus seeded
Gaussian noise.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from roadsurf.detection import stage
from roadsurf.detection.config import CrackConfig, DetectionConfig
from roadsurf.detection.crackraster import measure_crack_on_raster, stations_from_samples
from roadsurf.detection.mapframe import MapFrame
from roadsurf.io.drive import Camera
from roadsurf.io.formats import GridSpec, write_geotiff
from tests.detection.synthetic import Pothole, Scene, Trough, build

CFG = CrackConfig()
# 1.7 mm pixels: a 3 mm crack is about 2 px wide in the image
CAM = Camera(width=480, height=360, fx=600.0, fy=600.0, cx=239.5, cy=179.5, height_m=1.0, fps=10.0)


class ArraySource:
    """An in-memory residual raster (the ``WindowSource`` protocol)."""

    source = "test"

    def __init__(self, z: np.ndarray, gsd: float) -> None:
        self.z = z.astype(np.float32)
        self.grid = GridSpec("local ENU", 0.0, z.shape[0] * gsd, gsd, z.shape[1], z.shape[0])

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        return self.z[r0 : r0 + h, c0 : c0 + w].copy()

    def close(self) -> None:
        return None


def _raster(scene: Scene, gsd: float, size_m: float, noise_m: float, seed: int) -> ArraySource:
    """Residual (m, negative below) of ``scene`` on a size x size grid from (0, 0), as the dense
    surface shows it: box-averaged over the footprint, plus noise."""
    n = int(round(size_m / gsd))
    y, x = np.mgrid[0:n, 0:n]
    e = (x + 0.5) * gsd
    north = size_m - (y + 0.5) * gsd
    z = -scene.depth(e, north)
    z = uniform_filter(z, size=int(round(CFG.raster_footprint_cells)))
    z += np.random.default_rng(seed).normal(0.0, noise_m, z.shape)
    return ArraySource(z, gsd)


def _samples(t: Trough, seed: int, spread_m: float = 0.001) -> np.ndarray:
    """Map samples along the crack's centre line, scattered like mapped 2D pieces."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0, 1, 400)
    xy = np.c_[t.x0_m + s * (t.x1_m - t.x0_m), t.y0_m + s * (t.y1_m - t.y0_m)]
    return xy + rng.normal(0, spread_m, xy.shape)


def test_stations_follow_the_crack():
    t = Trough(0.1, 0.2, 0.5, 0.5, 0.01, 0.005)
    st, nrm = stations_from_samples(_samples(t, 0), 0.005)
    assert len(st) > 50  # 0.5 m at 5 mm steps, the lattice's diagonal cells included
    along = np.array([0.4, 0.3]) / 0.5
    assert np.all(np.abs(nrm @ along) < 0.1)  # normals across the crack


@pytest.mark.parametrize("seed", [1, 2])
def test_wide_crack_is_measured_on_a_fine_raster(seed):
    """16 mm wide, 6 mm deep on a 1 mm raster: resolved; width and depth from the profiles."""
    t = Trough(0.1, 0.2, 0.5, 0.5, 0.016, 0.006)
    src = _raster(Scene(troughs=[t]), 0.001, 0.7, 0.0003, seed)
    m = measure_crack_on_raster(src, _samples(t, seed), 0.012, CFG)  # image width 25 % narrow
    assert m.source == "raster", m
    assert m.width_m == pytest.approx(0.016, rel=0.2)
    assert m.max_depth_m == pytest.approx(0.006, abs=0.0006)
    assert m.profiles > 60


def test_narrow_crack_is_not_resolved_on_the_default_raster():
    """5 mm wide on a 3.7 mm raster: the footprint averages it away; the pairs' figures stay."""
    t = Trough(0.1, 0.2, 0.5, 0.5, 0.005, 0.005)
    src = _raster(Scene(troughs=[t]), 0.0037, 0.7, 0.0005, 3)
    m = measure_crack_on_raster(src, _samples(t, 3), 0.005, CFG)
    assert m.source == "points" and np.isnan(m.max_depth_m)
    assert m.profiles > 30  # read, just not resolved


def test_flat_road_gives_no_raster_crack():
    src = _raster(Scene(), 0.001, 0.7, 0.0003, 4)
    t = Trough(0.1, 0.2, 0.5, 0.5, 0.016, 0.006)
    assert measure_crack_on_raster(src, _samples(t, 4), 0.016, CFG).source == "points"


def test_unobserved_raster_keeps_the_pairs_figures():
    t = Trough(0.1, 0.2, 0.5, 0.5, 0.016, 0.006)
    src = _raster(Scene(troughs=[t]), 0.001, 0.7, 0.0003, 5)
    src.z[:] = np.nan
    m = measure_crack_on_raster(src, _samples(t, 5), 0.016, CFG)
    assert m.source == "points" and m.profiles == 0


def _write_surface(run_dir, scene: Scene, traj, gsd: float, seed: int) -> None:
    """RUN/surface.tif: the scene's residual as the dense surface shows it, in the map frame."""
    mframe = MapFrame.create(traj.reference)
    lo = mframe.grid_from_enu(np.array([[-0.5, -0.4, 0.0]]))[0]
    n_e, n_n = int(0.9 / gsd), int(1.6 / gsd)
    grid = GridSpec(mframe.crs, float(lo[0]), float(lo[1]) + n_n * gsd, gsd, n_e, n_n)
    r, c = np.mgrid[0:n_n, 0:n_e]
    xy = grid.xy_from_rowcol(r.ravel(), c.ravel())
    enu = mframe.enu_from_grid(xy)
    z = -scene.depth(enu[:, 0], enu[:, 1]).reshape(n_n, n_e)
    z = uniform_filter(z, size=int(round(CFG.raster_footprint_cells)))
    z += np.random.default_rng(seed).normal(0.0, 0.0003, z.shape)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_geotiff(run_dir / "surface.tif", z.astype(np.float32), grid, nodata=float("nan"))


def test_3mm_crack_and_40mm_pothole_on_a_rendered_drive(tmp_path):
    """A 3 mm wide, 3 mm deep crack and a 40 mm pothole, six rendered frames 0.15 m apart, a
    1 mm dense-like surface.tif: the crack is found once, its length within 20 % and its depth
    and width within a few mm (the raster does not resolve it: the pairs measure it); the
    pothole's depth within 3 mm; a 16 mm crack beside them is measured on the raster."""
    thin = Trough(-0.25, 0.55, 0.15, 0.58, 0.003, 0.003, darker=0.5, dark_profile="floor")
    wide = Trough(-0.3, 0.85, 0.1, 0.9, 0.016, 0.006, darker=0.5, dark_profile="floor")
    pot = Pothole(0.2, 0.2, 0.1, 0.04)
    scene = Scene(troughs=[thin, wide], potholes=[pot])
    drive, pairs, traj = build(scene, tmp_path / "drive", n_frames=8, camera=CAM, step_m=0.15)
    _write_surface(tmp_path / "run", scene, traj, 0.001, 7)
    res = stage.run(DetectionConfig(), drive, pairs, traj, tmp_path / "run")
    cracks = sorted((d for d in res.defects if d.type == "crack"), key=lambda d: d.width_m)
    pots = [d for d in res.defects if d.type == "pothole"]
    assert len(cracks) == 2 and len(pots) == 1, res.table()
    c3, c16 = cracks
    assert c3.length_m == pytest.approx(np.hypot(0.40, 0.03), rel=0.2)
    assert c3.width_m == pytest.approx(0.003, abs=0.002)
    assert 0.0015 < c3.max_depth_m <= 0.0035  # a lower bound: points straddle the groove
    assert c3.measured_on == "points" and c3.profiles > 0
    assert c16.measured_on == "raster", c16
    assert c16.width_m == pytest.approx(0.016, rel=0.2)
    assert c16.max_depth_m == pytest.approx(0.006, abs=0.001)
    assert pots[0].max_depth_m == pytest.approx(0.04, abs=0.003)


def test_crack_target_counts_length_within_20_percent():
    """evaluation: true cracks >= 3 mm wide and deep, detected, length within 20 %."""
    from roadsurf.evaluation.detection import _crack_target

    def crack(w, d, length):
        return (None, {"type": "crack", "width_m": w, "max_depth_m": d, "length_m": length})

    truths = [crack(0.004, 0.004, 1.0), crack(0.003, 0.002, 1.0), crack(0.005, 0.003, 0.5)]
    preds = [crack(0.004, 0.003, 1.15), crack(0.004, 0.002, 0.9), crack(0.005, 0.002, 0.35)]
    # the shallow truth is outside the target; the third's length is 30 % short
    assert _crack_target(preds, truths, [(0, 0), (1, 1), (2, 2)]) == {
        "truth": 2,
        "detected": 2,
        "length_within_20pct": 1,
    }
