"""Ruts traced on straightedge profiles (detection.ruts) on seeded synthetic residual rasters."""

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.mapseg import Region
from roadsurf.detection.rutrecord import longest_trough_m
from roadsurf.detection.ruts import trace_ruts
from roadsurf.detection.rutscan import scan_seeds
from roadsurf.detection.ruttrace import trace_rut
from roadsurf.io.formats import GridSpec

CFG = DetectionConfig()
GSD = 0.005


class ArraySource:
    """An in-memory residual raster read by windows (the WindowSource protocol)."""

    def __init__(self, res: np.ndarray) -> None:
        self.res = res.astype(np.float32)
        self.grid = GridSpec("LOCAL_ENU", 0.0, res.shape[0] * GSD, GSD, res.shape[1], res.shape[0])
        self.source = "test"
        self.reads = 0

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        self.reads += 1
        return self.res[r0 : r0 + h, c0 : c0 + w].copy()

    def close(self) -> None:
        pass


def _road(width_m=2.0, length_m=9.0, noise_m=0.001, seed=0):
    """Residual raster (rows = north, top row = largest y) and its cell centres (x, y)."""
    h, w = int(length_m / GSD), int(width_m / GSD)
    rng = np.random.default_rng(seed)
    # Raster noise is spatially correlated (interpolated sparse points): white noise smoothed
    # by one cell, rescaled to the requested σ.
    n = ndimage.gaussian_filter(rng.normal(0, 1, (h, w)), 1.0)
    res = noise_m * n / n.std()
    rows, cols = np.mgrid[0:h, 0:w]
    x = (cols + 0.5) * GSD
    y = (h - rows - 0.5) * GSD
    return res, x, y


def _rut(x, y, depth_m, width_m, y0, y1, bend_m=0.15, taper_m=0.5):
    """Depth of a gently curving rut along y from y0 to y1, (1 - q²)² cross-section."""
    xc = 1.0 + bend_m * np.sin(np.pi * (y - y0) / (y1 - y0))
    q = np.clip(2 * np.abs(x - xc) / width_m, 0, 1)
    along = np.clip(np.minimum(y - y0, y1 - y) / taper_m, 0, 1)
    return depth_m * (1 - q**2) ** 2 * along**2 * (3 - 2 * along)


def _region(mask: np.ndarray, res: np.ndarray) -> Region:
    r, c = np.nonzero(mask)
    return Region(rows=r, cols=c, depth_m=-res[r, c], depth_smooth_m=-res[r, c])


def test_a_shallow_rut_is_traced_whole_from_a_small_piece():
    """A 9 mm rut, 0.45 m wide, 5 m long, curving by 15 cm, on 1 mm noise: a 6 cm blob where
    noise crossed T_d seeds a trace that follows the whole rut and reads its depth within
    1.5 mm; the deepest raster cell over the rut reads several mm too deep."""
    res, x, y = _road()
    d = _rut(x, y, 0.009, 0.45, 2.0, 7.0)
    res = res - d
    blob = (x - 1.0 - 0.15) ** 2 + (y - 4.5) ** 2 < 0.03**2
    source = ArraySource(res)
    tr = trace_rut(source, _region(blob, res), CFG.rut, CFG.map)
    assert tr is not None
    assert tr.length_m == pytest.approx(5.0, abs=0.8)  # tapered ends are shallower than 3 mm
    assert tr.max_depth_m == pytest.approx(0.009, abs=0.0015)
    w = float(np.median(tr.width_m[tr.in_rut]))
    assert w == pytest.approx(0.45, rel=0.25)
    # The cells follow the curve: their x is the rut's centre line at their y.
    xy = source.grid.xy_from_rowcol(tr.rows, tr.cols)
    xc = 1.0 + 0.15 * np.sin(np.pi * (xy[:, 1] - 2.0) / 5.0)
    assert np.abs(xy[:, 0] - xc).max() < 0.3
    assert np.median(np.abs(xy[:, 0] - xc)) < 0.1
    # The old reading, deepest cell of the outline, is biased deep by the noise.
    assert float((-res)[d > 0.002].max()) > 0.009 + 0.002


def test_rut_pieces_become_one_rut_and_potholes_stay():
    """Two pieces of one rut and a pothole: trace_ruts returns the pothole's region untouched
    and one rut region (Region.rut set) that holds both pieces' cells."""
    res, x, y = _road(seed=1)
    d = _rut(x, y, 0.012, 0.5, 1.5, 7.5, bend_m=0.0)
    pot = 0.03 * np.clip(1 - ((x - 1.0) ** 2 + (y - 8.4) ** 2) / 0.2**2, 0, None)
    res = res - np.maximum(d, pot)
    piece_a = (np.abs(x - 1.0) < 0.04) & (np.abs(y - 3.0) < 0.2)
    piece_b = (np.abs(x - 1.0) < 0.04) & (np.abs(y - 6.0) < 0.15)
    hole = pot > 0.008
    regions = [_region(piece_a, res), _region(piece_b, res), _region(hole, res)]
    ev = np.zeros((0, 2))
    out = trace_ruts(ArraySource(res), regions, CFG.rut, CFG.map, ev, np.zeros(0, int))
    ruts = [r for r in out if r.rut is not None]
    others = [r for r in out if r.rut is None]
    assert len(ruts) == 1 and len(others) == 1
    assert others[0] is regions[2]
    rut = ruts[0]
    assert rut.rut.max_depth_m == pytest.approx(0.012, abs=0.0015)
    assert rut.rut.length_m == pytest.approx(6.0, abs=0.8)
    keys = set((rut.rows * 10_000 + rut.cols).tolist())
    for piece in (piece_a, piece_b):
        r, c = np.nonzero(piece)
        assert len(keys & set((r * 10_000 + c).tolist())) >= 0.9 * len(r)


def test_no_rut_on_flat_road_or_from_a_pothole():
    """Noise blobs on flat road and a round pothole seed no trace; disabled, nothing changes."""
    res, x, y = _road(seed=2)
    pot = 0.04 * np.clip(1 - ((x - 1.0) ** 2 + (y - 4.0) ** 2) / 0.3**2, 0, None)
    res = res - pot
    source = ArraySource(res)
    noise_blob = (x - 0.5) ** 2 + (y - 6.5) ** 2 < 0.03**2
    long_blob = (np.abs(x - 1.5) < 0.02) & (np.abs(y - 2.0) < 0.3)  # elongated, on flat road
    hole = pot > 0.008
    for mask in (noise_blob, long_blob, hole):
        assert trace_rut(source, _region(mask, res), CFG.rut, CFG.map) is None
    regions = [_region(m, res) for m in (noise_blob, long_blob, hole)]
    ev = np.zeros((0, 2))
    out = trace_ruts(source, regions, CFG.rut, CFG.map, ev, np.zeros(0, int))
    # The same region objects come back (list == would compare numpy fields element-wise).
    assert len(out) == len(regions) and all(a is b for a, b in zip(out, regions, strict=True))
    off = dataclasses.replace(CFG.rut, enabled=False)
    assert trace_ruts(source, regions, off, CFG.map, ev, np.zeros(0, int)) is regions


def test_a_sag_wider_than_the_straightedge_is_not_a_rut():
    """A 1.4 m wide, 10 mm deep depression along the road is a sag (wider than max_width_m
    and than the straightedge): no rut is traced through it."""
    res, x, y = _road(width_m=3.0, seed=3)
    res = res - _rut(x, y, 0.010, 1.4, 1.5, 7.5, bend_m=0.0) * (x < 3.0)
    blob = (np.abs(x - 1.0) < 0.05) & (np.abs(y - 4.0) < 0.05)
    assert trace_rut(ArraySource(res), _region(blob, res), CFG.rut, CFG.map) is None


def _bowl(x, y, x0, y0, a_m, b_m, depth_m):
    """A pothole: paraboloid of semi-axes a_m (across) and b_m (along), depth_m deep."""
    return depth_m * np.clip(1 - ((x - x0) / a_m) ** 2 - ((y - y0) / b_m) ** 2, 0, None)


def test_two_potholes_in_a_line_are_not_a_rut():
    """Two potholes (48 and 30 mm deep) in a line, 0.58 m apart with a strip of flat road
    between them: the trace from a narrow piece of one crosses into the other and is 1.1 m
    long, past rut_min_length_m, but the road comes back to its level in between, so both
    stay potholes. With the flat-gap check off the pair reads as one rut."""
    res, x, y = _road(seed=6)
    a = _bowl(x, y, 1.0, 4.0, 0.16, 0.22, 0.05)
    b = _bowl(x, y, 1.0, 4.58, 0.24, 0.28, 0.03)
    res = res - np.maximum(a, b)
    source = ArraySource(res)
    piece = _region((a > 0.008) & (np.abs(x - 1.0) < 0.04), res)
    other = _region(b > 0.008, res)
    tr = trace_rut(source, piece, CFG.rut, CFG.map)
    assert tr is not None and tr.measured_length_m > CFG.map.rut_min_length_m
    assert longest_trough_m(tr, CFG.rut) == pytest.approx(0.55, abs=0.15)
    ev, ev_pair = np.zeros((0, 2)), np.zeros(0, int)
    out = trace_ruts(source, [piece, other], CFG.rut, CFG.map, ev, ev_pair)
    assert len(out) == 2 and all(r.rut is None for r in out)
    off = dataclasses.replace(CFG.rut, flat_gap_frac=0.0)
    out = trace_ruts(source, [piece, other], off, CFG.map, ev, ev_pair)
    assert [r.rut is not None for r in out] == [True]


def test_a_rut_that_shallows_midway_is_one_rut():
    """A 12 mm rut that shallows to 5 mm over 0.3 m midway is still one rut: its depth never
    comes back to the road level."""
    res, x, y = _road(seed=7)
    d = _rut(x, y, 0.012, 0.5, 1.5, 7.5, bend_m=0.0)
    dip = 1 - 0.6 * np.clip(1 - np.abs(y - 4.5) / 0.3, 0, 1)
    res = res - d * dip
    piece = (np.abs(x - 1.0) < 0.04) & (np.abs(y - 3.0) < 0.2)
    source = ArraySource(res)
    tr = trace_rut(source, _region(piece, res), CFG.rut, CFG.map)
    assert tr is not None
    assert longest_trough_m(tr, CFG.rut) == pytest.approx(tr.measured_length_m)
    ev, ev_pair = np.zeros((0, 2)), np.zeros(0, int)
    out = trace_ruts(source, [_region(piece, res)], CFG.rut, CFG.map, ev, ev_pair)
    assert len(out) == 1 and out[0].rut is not None
    assert out[0].rut.length_m == pytest.approx(6.0, abs=0.8)


def test_the_drive_scan_finds_a_rut_too_shallow_for_any_seed():
    """A 7 mm rut never crosses T_d (8 mm), so segmentation gives no region; the scan of
    transverse profiles along the drive seeds it and the trace measures it. On flat road the
    scan finds no rut."""
    path = np.column_stack([np.full(60, 1.0), np.linspace(0.3, 8.7, 60)])
    res, x, y = _road(seed=4)
    source = ArraySource(res - _rut(x, y, 0.007, 0.5, 2.0, 7.5, bend_m=0.1))
    seeds = scan_seeds(source, path, CFG.rut, CFG.map)
    assert seeds
    ev = np.zeros((0, 2))
    out = trace_ruts(source, [], CFG.rut, CFG.map, ev, np.zeros(0, int), scan_seeds=seeds)
    assert len(out) == 1 and out[0].rut is not None
    assert out[0].rut.max_depth_m == pytest.approx(0.007, abs=0.0015)
    assert out[0].rut.length_m == pytest.approx(5.5, abs=1.0)
    flat = ArraySource(_road(seed=5)[0])
    seeds = scan_seeds(flat, path, CFG.rut, CFG.map)
    assert trace_ruts(flat, [], CFG.rut, CFG.map, ev, np.zeros(0, int), scan_seeds=seeds) == []
    with pytest.raises(ValueError, match="path_xy_m"):
        scan_seeds(flat, path.ravel(), CFG.rut, CFG.map)


def test_the_scan_reads_only_the_mapped_stretches():
    """A fused run maps only the stretches it reconstructed: scan lines outside ``observed``
    are not read, and the seeds are those of the full scan (the unmapped road is NaN)."""
    from shapely.geometry import box

    path = np.column_stack([np.full(60, 1.0), np.linspace(0.3, 8.7, 60)])
    res, x, y = _road(seed=4)
    res = res - _rut(x, y, 0.007, 0.5, 2.0, 7.5, bend_m=0.1)
    res[(y < 1.0) | (y > 8.0)] = np.nan  # the ends of the drive were not reconstructed
    full, part = ArraySource(res), ArraySource(res)
    seeds = scan_seeds(full, path, CFG.rut, CFG.map)
    mapped = scan_seeds(part, path, CFG.rut, CFG.map, observed=box(0.0, 1.0, 2.0, 8.0))
    assert seeds and len(mapped) == len(seeds)
    for a, b in zip(seeds, mapped, strict=True):
        assert np.array_equal(a.rows, b.rows) and np.array_equal(a.cols, b.cols)
    assert 0 < part.reads <= full.reads
    # nothing mapped near the drive: nothing read, no seed
    far = ArraySource(res)
    assert scan_seeds(far, path, CFG.rut, CFG.map, observed=box(10.0, 0.0, 11.0, 9.0)) == []
    assert far.reads == 0


@pytest.mark.parametrize("seed", [0, 1])
def test_tapered_rut_ends_are_extrapolated_to_depth_zero(seed):
    """A 10 mm rut, 5 m long, whose depth ramps up over 0.8 m at each end (smoothstep): the
    trace stops where the ramp crosses its threshold (~3 mm), 0.25-0.3 m short of each end.
    The ends are extrapolated from the threshold and twice it, like the width, which brings
    the length within 0.25 m; an abrupt end gains at most a station."""
    res, x, y = _road(seed=seed)
    blob = (x - 1.0 - 0.15) ** 2 + (y - 4.5) ** 2 < 0.03**2
    tapered = res - _rut(x, y, 0.010, 0.5, 2.0, 7.0, taper_m=0.8)
    off = dataclasses.replace(CFG.rut, extrapolate_ends=False)
    tr0 = trace_rut(ArraySource(tapered), _region(blob, tapered), off, CFG.map)
    tr = trace_rut(ArraySource(tapered), _region(blob, tapered), CFG.rut, CFG.map)
    assert tr0 is not None and tr is not None
    assert tr0.length_m < 4.6
    assert abs(tr.length_m - 5.0) < 0.25
    assert tr.measured_length_m == pytest.approx(tr0.length_m)
    assert min(tr.end_extension_m) > 0.05
    assert len(tr.rows) > len(tr0.rows)  # the ends' cells are part of the rut's area
    abrupt = res - _rut(x, y, 0.010, 0.5, 2.0, 7.0, taper_m=0.01)
    tra = trace_rut(ArraySource(abrupt), _region(blob, abrupt), CFG.rut, CFG.map)
    assert tra is not None
    assert max(tra.end_extension_m) <= 1.5 * CFG.rut.step_m
    assert tra.length_m < 5.2


def test_a_rut_across_a_striped_map_is_one_rut():
    """Frames overlapping by less than half leave a map of strips: here 0.2 m observed every
    0.6 m along a 12 mm rut. Its pieces are elongated across the track (the strip is narrower
    than the rut is wide). trace_ruts follows the rut through the unobserved stretches and
    returns one rut, its outline bridged across the holes; without that (max_unobserved_m 0)
    each strip stays a separate region."""
    res, x, y = _road(seed=4)
    res = res - _rut(x, y, 0.012, 0.5, 1.5, 7.5, bend_m=0.0, taper_m=0.3)
    strip = np.mod(y, 0.6) < 0.2
    res = np.where(strip, res, np.nan)
    d = -res
    pieces = []
    for y0 in np.arange(1.8, 7.2, 0.6):
        m = strip & (y > y0) & (y < y0 + 0.3) & (np.nan_to_num(d) > 0.008)
        if m.sum() > 20:
            pieces.append(_region(m, res))
    assert len(pieces) >= 8
    ev = np.zeros((0, 2))
    out = trace_ruts(ArraySource(res), pieces, CFG.rut, CFG.map, ev, np.zeros(0, int))
    ruts = [r for r in out if r.rut is not None]
    assert len(ruts) == 1 and len(out) == 1
    tr = ruts[0].rut
    assert tr.length_m == pytest.approx(6.0, abs=0.6)
    assert tr.max_depth_m == pytest.approx(0.012, abs=0.0015)
    # the outline is continuous: cells between the strips too
    cy = ArraySource(res).grid.xy_from_rowcol(ruts[0].rows, ruts[0].cols)[:, 1]
    assert np.mean(np.mod(cy, 0.6) >= 0.2) > 0.5
    off = dataclasses.replace(CFG.rut, max_unobserved_m=0.0)
    out0 = trace_ruts(ArraySource(res), pieces, off, CFG.map, ev, np.zeros(0, int))
    assert not any(r.rut is not None and r.rut.length_m > 3.0 for r in out0)
