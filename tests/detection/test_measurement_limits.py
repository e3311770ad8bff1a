"""measure_regions at its limits (fourth fault battery): a traced rut on a rough road keeps its
own evidence, a defect reaching the dense surface's search depth is measured past it and said,
a region dropped as deeper than any defect is said, not silent."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.mapseg import Region, Segmentation
from roadsurf.detection.measurement import measure_regions
from roadsurf.detection.rutrecord import RutTrace
from roadsurf.io.formats import GridSpec

GSD = 0.005


def _bowl(depth_m: float, radius_m: float = 0.15) -> tuple[GridSpec, Region]:
    grid = GridSpec("EPSG:32617", -0.5, 0.5, GSD, 200, 200)
    rr, cc = np.meshgrid(np.arange(200), np.arange(200), indexing="ij")
    xy = grid.xy_from_rowcol(rr.ravel(), cc.ravel())
    r = np.linalg.norm(xy, axis=1)
    raw = depth_m * np.clip((radius_m - r) / 0.03, 0.0, 1.0)
    ins = raw > 0
    reg = Region(rows=rr.ravel()[ins], cols=cc.ravel()[ins], depth_m=raw[ins],
                 depth_smooth_m=raw[ins], noise_m=0.001, seed_m=0.008)  # fmt: skip
    return grid, reg


def test_a_traced_rut_needs_no_pothole_point_support() -> None:
    """The rough road's case: the pairs' T_d (13.9 mm) above the 10.6 mm rut leaves it no
    defect points; its straightedge trace is its evidence. A pothole region alike is vetoed."""
    grid = GridSpec("EPSG:32617", -0.5, 2.0, GSD, 100, 600)
    rows = np.repeat(np.arange(40, 60), 500)
    cols = np.tile(np.arange(50, 550), 20)
    depth = np.full(len(rows), 0.0106)
    n_st = 12
    trace = RutTrace(
        centres_xy_m=np.c_[np.linspace(-0.2, 2.2, n_st), np.full(n_st, 0.25)],
        depth_m=np.full(n_st, 0.0106), width_m=np.full(n_st, 0.4), noise_m=np.full(n_st, 0.004),
        in_rut=np.ones(n_st, bool), length_m=2.5, max_depth_m=0.0106, rows=rows, cols=cols,
    )  # fmt: skip
    regs = [
        Region(rows=rows, cols=cols, depth_m=depth, depth_smooth_m=depth, noise_m=0.0035,
               seed_m=0.0139, rut=trace),
        Region(rows=rows, cols=cols, depth_m=depth, depth_smooth_m=depth, noise_m=0.0035,
               seed_m=0.0139),
    ]  # fmt: skip
    seg = Segmentation(0.0035, 0.0139, 0.0035, regs, grid)
    defects, _ = measure_regions(DetectionConfig(), seg, {}, have_pairs=True)
    assert [d.type for d in defects] == ["rut"]
    assert defects[0].max_depth_m == pytest.approx(0.0106)


def test_a_defect_at_the_surface_search_depth_is_said() -> None:
    """A 240 mm pothole on a surface searched to 120 mm: the surface is flat at ~120 mm and the
    points read 235 mm (the dense tracks did too; they were cut to the surface's 120 mm without
    a word: the battery's drive, docs/detection.md). The warning names the setting."""
    grid, reg = _bowl(0.121)
    seg = Segmentation(0.001, 0.008, 0.0015, [reg], grid)
    xy = grid.xy_from_rowcol(reg.rows, reg.cols)
    inner = np.linalg.norm(xy, axis=1) < 0.1
    points = (xy[inner], np.full(int(inner.sum()), -0.235))
    warns: list[str] = []
    kw = {"have_pairs": False, "points": points, "dense_raster": True, "warnings": warns}
    got, _ = measure_regions(DetectionConfig(), seg, {}, raster_floor_m=0.12, **kw)
    assert got[0].max_depth_m == pytest.approx(0.235, abs=0.002)
    assert len(warns) == 1 and "mapping.dense.max_depth_m" in warns[0], warns
    assert "search depth (120 mm" in warns[0] and "235 mm" in warns[0]
    # the same surface with a deeper search, or none known: nothing to say
    for floor in (0.30, float("nan")):
        warns.clear()
        got, _ = measure_regions(DetectionConfig(), seg, {}, raster_floor_m=floor, **kw)
        assert got[0].max_depth_m == pytest.approx(0.235, abs=0.002) and warns == []


def test_a_region_deeper_than_any_defect_is_dropped_with_a_warning() -> None:
    grid, reg = _bowl(0.30)
    seg = Segmentation(0.001, 0.008, 0.0015, [reg], grid)
    warns: list[str] = []
    defects, _ = measure_regions(DetectionConfig(), seg, {}, have_pairs=False, warnings=warns)
    assert defects == []
    assert len(warns) == 1 and "detection.plane.max_depth_m (250 mm)" in warns[0], warns
    assert "300 mm deep was dropped" in warns[0]


def test_a_region_the_dense_surface_reads_that_deep_is_kept() -> None:
    """A 260 mm floor on a fused dense surface searched to 480 mm: the surface's own reading,
    not a failed reconstruction's points. Searched to 120 mm only (or on a sparse raster) the
    same region is the mismatch bound's."""
    grid, reg = _bowl(0.26)
    seg = Segmentation(0.001, 0.008, 0.0015, [reg], grid)
    warns: list[str] = []
    kw = {"have_pairs": False, "dense_raster": True, "warnings": warns}
    defects, _ = measure_regions(DetectionConfig(), seg, {}, raster_floor_m=0.48, **kw)
    assert len(defects) == 1 and defects[0].max_depth_m == pytest.approx(0.26)
    assert warns == []
    defects, _ = measure_regions(DetectionConfig(), seg, {}, raster_floor_m=0.12, **kw)
    assert defects == [] and "260 mm deep was dropped" in warns[0]
