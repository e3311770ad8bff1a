"""Windowed map segmentation (detection.windows): bounded reads, defects whole across windows,
and the refined 2D masks written per frame."""

import dataclasses

import cv2
import numpy as np
import pytest

from roadsurf.detection import stage
from roadsurf.detection.config import DetectionConfig, MapSegmentConfig
from roadsurf.detection.mapseg import Region
from roadsurf.detection.windows import (
    PointsSource,
    candidate_windows,
    merge_regions,
    segment_windows,
)
from roadsurf.io.formats import GridSpec
from tests.detection.synthetic import Pothole, Scene, Trough, build, write_surface

CFG = DetectionConfig()


def _surface_run(tmp_path, scene, cfg):
    drive, pairs, traj = build(scene, tmp_path / "drive")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    write_surface(scene, run_dir, traj)
    return stage.run(cfg, drive, pairs, traj, run_dir)


def test_defects_come_out_whole_across_small_windows(tmp_path):
    """With blocks much smaller than the defects (15 cm; the margin is raised to the 0.6 m
    re-levelling window) the pothole and the 1.7 m rut are cut by many window borders; merged,
    they measure like with the default windows."""
    scene = Scene(
        potholes=[Pothole(0.15, 0.9, 0.15, 0.045)],
        troughs=[Trough(-0.3, 0.2, -0.3, 1.9, 0.25, 0.018)],
    )
    big = _surface_run(tmp_path / "big", scene, CFG)
    small_map = dataclasses.replace(CFG.map, window_core_m=0.15, window_margin_m=0.1)
    small = _surface_run(tmp_path / "small", scene, dataclasses.replace(CFG, map=small_map))
    assert sorted(d.type for d in big.defects) == ["pothole", "rut"]
    assert sorted(d.type for d in small.defects) == ["pothole", "rut"], small.table()
    for a, b in zip(
        sorted(big.defects, key=lambda d: d.type),
        sorted(small.defects, key=lambda d: d.type),
        strict=True,
    ):
        assert b.area_m2 == pytest.approx(a.area_m2, rel=0.1)
        assert b.length_m == pytest.approx(a.length_m, rel=0.1)
        assert b.max_depth_m == pytest.approx(a.max_depth_m, abs=0.002)


def test_reads_stay_near_the_candidates():
    """A 200 m long sparse corridor: only windows around the seeded place are read."""
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 200, 200_000)
    y = rng.uniform(0, 1.0, len(x))
    res = rng.normal(0, 0.001, len(x))
    hole = np.hypot(x - 100.0, y - 0.5) < 0.15
    res[hole] -= 0.03
    src = PointsSource(np.c_[x, y], res, 0.01, "EPSG:32617", "test")
    reads: list[int] = []
    orig = src.read

    def counting(r0, c0, h, w):
        reads.append(h * w)
        return orig(r0, c0, h, w)

    src.read = counting
    seeds = np.c_[x[hole], y[hole]]
    seg = segment_windows(src, MapSegmentConfig(), seeds, seeds, np.zeros(len(seeds), int))
    full = src.grid.width * src.grid.height
    assert len(seg.regions) == 1
    assert sum(reads) < 0.05 * full
    assert max(reads) <= (300 + 2) ** 2  # (core + 2 margins) / 1 cm, squared


def test_candidate_windows_skip_isolated_points():
    grid = GridSpec("EPSG:32617", 0.0, 10.0, 0.01, 1000, 1000)
    pts = np.array([[2.0, 8.0], [2.05, 8.0], [2.1, 8.02], [7.0, 3.0]])
    rc = grid.rowcol_from_xy(pts)

    def covers(w, k):
        return w.r0 <= rc[k, 0] < w.r0 + w.h and w.c0 <= rc[k, 1] < w.c0 + w.w

    wins = candidate_windows(pts, grid, 1.0, 0.5, min_points=3)
    assert wins and all(w.h <= 200 and w.w <= 200 for w in wins)
    assert all(any(covers(w, k) for w in wins) for k in range(3))
    assert not any(covers(w, 3) for w in wins)  # the isolated point gets no window
    assert any(covers(w, 3) for w in candidate_windows(pts, grid, 1.0, 0.5, min_points=1))


def test_merge_regions_unions_touching_and_overlapping_cells():
    def reg(rows, cols, idx):
        r = Region(
            rows=np.array(rows),
            cols=np.array(cols),
            depth_m=np.ones(len(rows)),
            depth_smooth_m=np.ones(len(rows)),
        )
        r.support_idx = np.array(idx)
        r.noise_m, r.seed_m = 0.001, 0.008
        return r

    a = reg([5, 5, 6], [5, 6, 5], [0, 1])
    b = reg([7, 7], [6, 7], [1, 2])  # touches a diagonally at (6,5)-(7,6)
    c = reg([5, 20], [6, 20], [3])  # shares cell (5,6) with a
    d = reg([50], [50], [4])  # far away
    ev_pair = np.array([0, 0, 1, 2, 3])
    out = merge_regions([a, b, c, d], 100, ev_pair)
    assert len(out) == 2
    m = max(out, key=lambda r: len(r.rows))
    assert len(m.rows) == 6  # the shared cell counted once
    assert m.n_support_points == 4  # evidence point 1 counted once
    assert m.support_pairs == {0, 1, 2}


def test_refined_masks_are_written_per_frame_without_the_map(tmp_path):
    """frame_label "pair" (the dissertation's decision, no map): each pair's refined 2D mask
    of image a (with the map, the masks are the map's defects: test_framemasks)."""
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.030)], lane_x_m=-0.3)
    drive, pairs, traj = build(scene, tmp_path / "drive")
    run_dir = tmp_path / "run"
    stage.run(dataclasses.replace(CFG, frame_label="pair"), drive, pairs, traj, run_dir)
    masks = {p.stem: p for p in (run_dir / "masks").glob("*.png")}
    assert set(masks) == {pairs[k].frame_a.rsplit(".", 1)[0] for k in range(len(pairs))}
    area = {}
    for stem, p in masks.items():
        m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert m.dtype == np.uint8 and m.ndim == 2
        area[stem] = int((m > 0).sum())
    # The pothole is seen in frames 2 and 3 (as in test_stage); the lane marking never counts.
    assert area["000002"] > 0 and area["000003"] > 0
    assert area["000000"] == 0 and area["000001"] == 0


def _striped_regions(n_reg: int, side: int) -> list[Region]:
    """``n_reg`` square regions of side x side cells in a row, each touching the next."""
    out = []
    rr, cc = np.mgrid[0:side, 0:side]
    for i in range(n_reg):
        r = Region(
            rows=rr.ravel().astype(np.int64),
            cols=(cc.ravel() + i * side).astype(np.int64),
            depth_m=np.ones(side * side),
            depth_smooth_m=np.ones(side * side),
        )
        r.support_idx = np.array([i])
        r.noise_m, r.seed_m = 0.001, 0.008
        out.append(r)
    return out


def test_merge_regions_memory_stays_with_the_regions_not_9x_their_cells():
    """Issue 31 #10: merging linked the regions with one graph edge per touching cell and
    neighbour (9 x the cells, about 100 MB traced for 250k cells). Links are now unique
    region pairs: the traced peak is a small multiple of the cells' own keys."""
    import tracemalloc

    regions = _striped_regions(200, 32)  # 204,800 cells, one chain
    n_cells = sum(len(r.rows) for r in regions)
    ev_pair = np.arange(200)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        out = merge_regions(regions, 200 * 32, ev_pair)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert len(out) == 1 and len(out[0].rows) == n_cells
    assert out[0].support_pairs == set(range(200))
    # the merged region's own arrays (rows, cols, depths: 32 B/cell) and the int64 keys with
    # their sort are needed (about 110 B/cell); the old edge lists took about 590 B/cell
    assert peak < 160 * n_cells, f"merge_regions traced peak {peak / 2**20:.0f} MB"


class _ArraySource:
    """A residual raster, its per-cell count and σ held in memory (as RasterSource reads
    them)."""

    def __init__(
        self,
        res: np.ndarray,
        count: np.ndarray | None,
        gsd: float = 0.005,
        sigma: np.ndarray | None = None,
    ) -> None:
        self.res, self.count, self.sigma = res, count, sigma
        self.grid = GridSpec("EPSG:32617", 500000.0, 4800000.0, gsd, res.shape[1], res.shape[0])
        self.source, self.footprint_m = "surface.tif", 0.009

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        return self.res[r0 : r0 + h, c0 : c0 + w].copy()

    def read_count(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        return None if self.count is None else self.count[r0 : r0 + h, c0 : c0 + w]

    def read_sigma(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        return None if self.sigma is None else self.sigma[r0 : r0 + h, c0 : c0 + w]


def test_dense_support_counts_deep_cells_two_pairs_or_one_pair_twice_as_deep() -> None:
    """A region's dense support: its cells deeper than T_d that two or more pairs' dense
    heights share (surface_nobs >= 2), and those one pair measured (count 1) deeper than 2 T_d,
    as an area; filled cells (count 0) never; none without a count raster."""
    rng = np.random.default_rng(5)
    n = 240
    rr, cc = np.mgrid[0:n, 0:n]
    disc = (rr - 120) ** 2 + (cc - 120) ** 2 < 30**2
    count = np.ones((n, n), np.uint8)
    count[:, :120] = 2  # the left half seen by two pairs
    count[:60, :] = 0  # the top rows filled, not measured
    measured = disc & (rr >= 60)
    for depth in (0.03, 0.012):  # 3.75 and 1.5 x T_d (8 mm)
        res = rng.normal(0, 0.0003, (n, n)).astype(np.float32)
        res[disc] -= depth
        g = _ArraySource(res, count).grid
        seed = g.xy_from_rowcol(np.array([120]), np.array([120]))
        segs = {}
        for name, cnt in (("count", count), ("none", None)):
            src = _ArraySource(res, cnt)
            segs[name] = segment_windows(src, CFG.map, seed, seed, np.zeros(1, int), min_points=1)
        (reg,) = [r for r in segs["count"].regions if len(r.rows) > 1000]
        assert reg.seed_m == pytest.approx(0.008, abs=0.001)
        part = measured if depth > 2 * reg.seed_m else measured & (cc < 120)
        assert reg.dense_support_m2 == pytest.approx(part.sum() * 0.005**2, rel=0.1)
        assert all(r.dense_support_m2 == 0 for r in segs["none"].regions)


def test_seeds_need_a_measured_cell_deeper_than_its_own_noise() -> None:
    """A steep camera's far field: cells the dense matching left to the sparse fill (count 0)
    or measured with a σ of centimetres read decimetre "defects" (a fault battery, 55° at
    640 x 480: precision 0.42). A seed must be a measured cell deeper than noise_k x its own σ
    as well as T_d; a true pothole among well measured cells is found as before."""
    rng = np.random.default_rng(6)
    n = 240
    rr, cc = np.mgrid[0:n, 0:n]
    res = rng.normal(0, 0.0003, (n, n)).astype(np.float32)
    near = (rr - 60) ** 2 + (cc - 60) ** 2 < 20**2  # a 30 mm pothole, σ 1 mm, measured
    fill = (rr - 60) ** 2 + (cc - 180) ** 2 < 20**2  # 30 mm deep in the sparse fill (count 0)
    noisy = (rr - 180) ** 2 + (cc - 120) ** 2 < 20**2  # 30 mm deep, measured with σ 20 mm
    for m in (near, fill, noisy):
        res[m] -= 0.03
    count = np.ones((n, n), np.uint8)
    count[20:100, 140:220] = 0  # the fill and the noisy cells: a far field around each disc
    sigma = np.full((n, n), 0.001, np.float32)
    sigma[140:220, 80:160] = 0.02
    sigma[count == 0] = np.nan
    g = _ArraySource(res, count).grid
    # windows around all three (as around any pair's evidence), no evidence point inside them
    seeds = g.xy_from_rowcol(np.array([60, 60, 180]), np.array([60, 180, 120]))

    def found(src: _ArraySource) -> set[tuple[int, int]]:
        seg = segment_windows(src, CFG.map, seeds, None, None, min_points=1)
        return {(int(np.median(r.rows)) // 60, int(np.median(r.cols)) // 60) for r in seg.regions}

    assert found(_ArraySource(res, count, sigma=sigma)) == {(1, 1)}
    # without the count and σ rasters (a sparse surface), all three read as defects
    assert found(_ArraySource(res, None)) == {(1, 1), (1, 3), (3, 2)}


def test_raster_source_reads_the_road_model_cells_as_unknown(tmp_path) -> None:
    """surface.tif's cells one frame only saw hold the road model (0 at count 0): detection
    reads them as unknown; measured cells and filled ones (count 0, a non-zero height) stay."""
    from roadsurf.detection.windows import RasterSource
    from roadsurf.io.formats import write_geotiff

    g = GridSpec("EPSG:32617", 500000.0, 4800000.0, 0.005, 4, 2)
    res = np.array([[0.001, -0.02, 0.0, 0.0], [0.0004, 0.0, np.nan, 0.0]], np.float32)
    cnt = np.array([[2, 1, 0, 1], [0, 0, 0, 3]], np.uint8)
    write_geotiff(tmp_path / "surface.tif", res, g, nodata=float("nan"))
    src = RasterSource(tmp_path / "surface.tif")
    assert src.count_path is None
    np.testing.assert_array_equal(src.read(0, 0, 2, 4), res)  # no count raster: as written
    write_geotiff(tmp_path / "surface_nobs.tif", cnt, g, nodata=0)
    src = RasterSource(tmp_path / "surface.tif")
    got = src.read(0, 0, 2, 4)
    src.close()
    want = res.copy()
    want[0, 2] = want[1, 1] = np.nan  # the road model; a measured 0 (count 1 / 3) stays
    np.testing.assert_array_equal(got, want)
    # the cells' σ beside it (surface_sigma.tif, NaN where none), read window by window
    assert src.sigma_path is None and src.read_sigma(0, 0, 2, 4) is None
    sig = np.array([[0.001, 0.002, np.nan, 0.02], [np.nan, np.nan, np.nan, 0.004]], np.float32)
    write_geotiff(tmp_path / "surface_sigma.tif", sig, g, nodata=float("nan"))
    src = RasterSource(tmp_path / "surface.tif")
    np.testing.assert_array_equal(src.read_sigma(0, 1, 2, 3), sig[:, 1:])
    src.close()


@pytest.mark.parametrize("nodata", [float("nan"), -9999.0])
def test_raster_source_plain_read_equals_the_masked_read(tmp_path, nodata) -> None:
    """With NaN nodata a window is read without GDAL's mask (a quarter of the cost): the same
    values as the masked read, NaN in unwritten (sparse) blocks and nodata cells; another
    nodata value keeps the masked read."""
    import rasterio
    from rasterio.windows import Window

    from roadsurf.detection.windows import RasterSource
    from roadsurf.io.formats import geotiff_profile

    g = GridSpec("EPSG:32617", 500000.0, 4800000.0, 0.005, 600, 520)
    rng = np.random.default_rng(2)
    data = rng.normal(0, 0.003, (256, 300)).astype(np.float32)
    data[rng.random(data.shape) < 0.2] = nodata
    profile = geotiff_profile(g, 1, "float32", nodata)
    with rasterio.open(tmp_path / "surface.tif", "w", **profile) as d:
        d.write(data[None], window=Window(256, 0, 300, 256))  # the other blocks stay unwritten
    src = RasterSource(tmp_path / "surface.tif")
    assert src._plain == np.isnan(nodata)
    with rasterio.open(tmp_path / "surface.tif") as d:
        for r0, c0, h, w in [(0, 0, 520, 600), (100, 200, 300, 250), (300, 0, 200, 100)]:
            m = d.read(1, window=Window(c0, r0, w, h), masked=True)
            want = np.ma.filled(m.astype(np.float32), np.nan)
            got = src.read(r0, c0, h, w)
            assert got.dtype == np.float32
            np.testing.assert_array_equal(got, want)
        got = src.read(0, 0, 520, 600)
        assert np.isnan(got[:, :256]).all() and np.isnan(got[256:]).all()  # unwritten blocks
    src.close()


def test_a_pothole_cut_by_an_unknown_strip_is_one_defect_a_grazing_neighbour_is_not() -> None:
    """Below 50 % overlap a strip between two pairs' parts is unknown: the two halves of a
    pothole it cuts are joined across it (they meet it along their width), a second pothole
    whose corner grazes the strip stays apart, and measured road never bridges."""
    from scipy import ndimage

    from roadsurf.detection.mapbridge import bridged_components

    n = 200
    rr, cc = np.mgrid[0:n, 0:n]
    unknown = (cc >= 90) & (cc < 110)  # a 20-cell strip across the drive
    pothole = (rr - 60) ** 2 + (cc - 100) ** 2 < 40**2
    rim = pothole & ~unknown  # cut in two by the strip
    rim |= (rr - 150) ** 2 + (cc - 140) ** 2 < 31**2  # a neighbour: its corner at column 109
    rim &= ~unknown
    rim |= (rr >= 150) & (rr < 190) & (cc >= 20) & (cc < 60)  # a patch beyond measured road
    rim |= (rr >= 150) & (rr < 190) & (cc >= 64) & (cc < 90)  # touches the strip
    lab, k = ndimage.label(rim, structure=np.ones((3, 3), bool))
    groups = bridged_components(rim, lab, k, unknown, radius_px=12.0)
    left, right = lab[60, 70], lab[60, 130]
    neighbour, far_a, far_b = lab[150, 140], lab[170, 40], lab[170, 80]
    assert groups[left] == groups[right]
    assert groups[neighbour] != groups[right]
    assert groups[far_a] != groups[far_b]
    assert (bridged_components(rim, lab, k, unknown, radius_px=0.0) == np.arange(k + 1)).all()
