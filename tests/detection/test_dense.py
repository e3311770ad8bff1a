"""Dense measurement inside candidate defects (detection/dense.py, densepair.py, densecheck.py) on a two-view render with
true parallax, where the sparse matches miss the pothole floor."""

import dataclasses

import numpy as np
import pytest

from roadsurf.detection import stage
from roadsurf.detection.config import DenseConfig, DetectionConfig
from tests.detection.synthetic import Pothole, Scene, build_two_view, write_surface

DEPTH_M, RADIUS_M = 0.040, 0.12


def _scene_and_run(tmp_path):
    scene = Scene(potholes=[Pothole(0.05, 0.12, RADIUS_M, DEPTH_M)])
    drive, pairs, traj = build_two_view(scene, tmp_path / "drive")
    # The map's raster shaves the bottom (interpolation between sparse points): 26 of 40 mm.
    shaved = dataclasses.replace(
        scene, potholes=[dataclasses.replace(scene.potholes[0], depth_m=0.026)]
    )
    write_surface(shaved, tmp_path / "run", traj)
    return drive, pairs, traj


def test_pothole_floor_without_sparse_features_is_measured_densely(tmp_path):
    drive, pairs, traj = _scene_and_run(tmp_path)
    # The sparse points stop 12 mm down the walls: they cannot see the 40 mm bottom.
    assert (-pairs[0].plane_dist_m).max() < 0.015
    res = stage.run(DetectionConfig(), drive, pairs, traj, tmp_path / "run")
    assert len(res.defects) == 1
    d = res.defects[0]
    assert d.max_depth_m == pytest.approx(DEPTH_M, abs=0.003)
    # Bowl 1 - r²/R²: area π R², fill volume π R² D / 2, mean depth over the area D / 2.
    assert d.area_m2 == pytest.approx(np.pi * RADIUS_M**2, rel=0.15)
    assert d.volume_m3 == pytest.approx(np.pi * RADIUS_M**2 * DEPTH_M / 2, rel=0.15)
    assert d.mean_depth_m == pytest.approx(DEPTH_M / 2, rel=0.2)


@pytest.mark.parametrize("turn_deg", [60.0, -35.0])
def test_camera_turned_between_the_shots_is_measured_densely(tmp_path, turn_deg):
    """Real photographs: the camera turns by tens of degrees between two shots. Image b is
    warped onto a by the road homography before tracking, so LK's windows compare the same
    ground; tracked in b's own pixels they did not, and the dense road σ read 10-60 mm."""
    scene = Scene(potholes=[Pothole(0.05, 0.12, RADIUS_M, DEPTH_M)])
    drive, pairs, traj = build_two_view(scene, tmp_path / "drive", turn_b_deg=turn_deg)
    shaved = dataclasses.replace(
        scene, potholes=[dataclasses.replace(scene.potholes[0], depth_m=0.026)]
    )
    write_surface(shaved, tmp_path / "run", traj)
    res = stage.run(DetectionConfig(), drive, pairs, traj, tmp_path / "run")
    assert len(res.defects) == 1
    d = res.defects[0]
    assert d.max_depth_m == pytest.approx(DEPTH_M, abs=0.003)
    assert d.area_m2 == pytest.approx(np.pi * RADIUS_M**2, rel=0.15)


def test_without_dense_measurement_the_sparse_floor_reads_shallow(tmp_path):
    """The old behaviour (sparse points and the raster only) on the same scene: far too shallow,
    which is what the dense measurement fixes."""
    drive, pairs, traj = _scene_and_run(tmp_path)
    cfg = DetectionConfig(dense=DenseConfig(enabled=False))
    res = stage.run(cfg, drive, pairs, traj, tmp_path / "run")
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m < DEPTH_M - 0.010


def test_road_homography_is_fitted_when_the_estimator_stores_none(tmp_path):
    """Estimators without a stored H (colmap) still get dense readings: H is fitted on the
    pair's road matches."""
    drive, pairs, traj = _scene_and_run(tmp_path)
    pairs[0].H = np.full((3, 3), np.nan)
    res = stage.run(DetectionConfig(), drive, pairs, traj, tmp_path / "run")
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m == pytest.approx(DEPTH_M, abs=0.003)


def test_no_dense_reading_without_the_pair_geometry(tmp_path):
    """Pairs without a homography and a metric baseline give no dense reading: the stage falls
    back to the sparse points instead of failing."""
    from shapely.geometry import Point

    from roadsurf.detection.dense import DenseContext, measure_defect_dense

    drive, pairs, traj = _scene_and_run(tmp_path)
    pairs[0].H = np.full((3, 3), np.nan)
    pairs[0].t_b_from_a_m = np.zeros(3)
    xy = traj.world_from_cam[0][:2, 3] + pairs[0].points_cam_a_m[:, :2] * [1, -1]
    ctx = DenseContext(drive, pairs, [(0, xy, np.ones(len(xy), bool))], 0.0005)
    poly = Point(0.05, 0.12).buffer(RADIUS_M)
    assert measure_defect_dense(poly, ctx, DenseConfig(), 0.002) is None


def test_partial_dense_reading_still_counts_for_max_depth(tmp_path):
    """Below ``min_coverage`` the dense reading does not measure area and volume, but the
    bottom it did see still beats the sparse points (the deeper reading is kept)."""
    drive, pairs, traj = _scene_and_run(tmp_path)
    cfg = DetectionConfig(dense=DenseConfig(min_coverage=1.01))  # every reading "partial"
    res = stage.run(cfg, drive, pairs, traj, tmp_path / "run")
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m == pytest.approx(DEPTH_M, abs=0.003)


def test_distort_undistort_round_trip():
    """Tracks run on the raw (distorted) images; the pair's pixels are ideal pinhole ones."""
    from roadsurf.io.drive import Camera

    cam = Camera(640, 480, 600.0, 600.0, 319.5, 239.5, 1.1, 15.0, (-0.12, 0.03, 0.0005, -0.0005, 0))
    rng = np.random.default_rng(3)
    px = np.c_[rng.uniform(20, 620, 200), rng.uniform(20, 460, 200)]
    raw = cam.distort_px(px)
    assert np.abs(raw - px).max() > 5.0  # the lens moves the corners by pixels
    assert np.allclose(cam.undistort_px(raw), px, atol=0.05)


def test_tracks_that_slid_along_the_epipolar_line_are_dropped():
    """A rut running with the direction of travel gave tracks 0.3-4.5 m 'deep' that passed the
    forward-backward and epipolar checks (they slide along the line); one such cluster set the
    rut's max depth to 0.75 m. The neighbour check drops them and keeps a steep-walled bowl."""
    from roadsurf.detection.densecheck import consistent

    rng = np.random.default_rng(3)
    shape = (40, 60)
    v, u = np.mgrid[: shape[0], : shape[1]]
    r = np.hypot(u - 30, v - 20) / 12.0
    # 40 mm bowl with a near-vertical 10 mm step at its rim, plus 1 mm noise
    depth = np.where(r < 1, 0.010 + 0.030 * (1 - r**2), 0.0) + rng.normal(0, 0.001, shape)
    d = depth.ravel().copy()
    spikes = rng.choice(d.size, 40, replace=False)
    d[spikes] = rng.uniform(0.3, 4.5, spikes.size)
    d[np.ravel_multi_index((21, 31), shape)] = 0.9  # one inside the bowl, too
    use = np.ones(d.size, bool)
    ok = np.ones(d.size, bool)
    keep = consistent(d, ok, use, shape, 0.001)
    assert not keep[spikes].any()
    assert not keep[np.ravel_multi_index((21, 31), shape)]
    good = np.setdiff1d(np.arange(d.size), spikes)
    assert keep[good].mean() > 0.97
    kept_max = d[keep].max()
    assert kept_max == pytest.approx(0.040, abs=0.004)


def test_patches_of_tracks_that_slid_together_are_dropped():
    """Motion blur along the direction of travel (9 m/s, 2 ms shutter) left patches of 4-12
    tracks 94-215 mm 'deep' in a 38 mm pothole, where LK failed around them: they agree with
    each other, so the 5 x 5 neighbour check keeps them, and one set the depth to 122 mm. An
    island of tracks where LK failed all around, and a small patch far deeper than the valid
    tracks around it, are dropped; a steep-walled floor and a narrow crack groove stay."""
    from roadsurf.detection.densecheck import consistent, no_deep_patch

    rng = np.random.default_rng(5)
    shape = (60, 80)
    v, u = np.mgrid[: shape[0], : shape[1]]
    r = np.hypot(u - 40, v - 30) / 20.0
    # 38 mm flat-floored pothole with near-vertical walls (profile 1 - r^6), a 4 mm deep crack
    # groove 2 tracks wide across the road beside it, 1 mm noise
    depth = np.where(r < 1, 0.038 * (1 - r**6), 0.0)
    depth[:, 4:6] = 0.004
    depth = depth + rng.normal(0, 0.001, shape)
    d = depth.ravel().copy()
    ok = np.ones(d.size, bool)
    # (a) a 5 x 5 patch of tracks at 120-150 mm inside the floor, among valid tracks
    patch = np.ravel_multi_index(np.mgrid[28:33, 44:49].reshape(2, -1), shape)
    d[patch] = rng.uniform(0.12, 0.15, patch.size)
    # (b) an island: LK failed on a 15 x 15 block of the floor but for 9 tracks at ~140 mm
    block = np.zeros(shape, bool)
    block[15:30, 20:35] = True
    ok[np.flatnonzero(block)] = False
    island = np.ravel_multi_index(np.mgrid[21:24, 26:29].reshape(2, -1), shape)
    ok[island] = True
    d[island] = rng.uniform(0.13, 0.15, island.size)
    use = np.ones(d.size, bool)
    keep = ok & consistent(d, ok, use, shape, 0.001)
    # the neighbour check alone keeps the patch's core and the whole island
    assert keep[patch].sum() >= 9 and keep[island].all()
    keep &= no_deep_patch(d, keep, use, shape, 0.001, half=6)
    assert not keep[patch].any()
    assert not keep[island].any()
    floor = ok & (r.ravel() < 0.9)
    floor[patch] = False
    assert keep[floor].mean() > 0.97  # the floor, walls included, stays
    groove = np.zeros(shape, bool)
    groove[:, 4:6] = True
    assert keep[groove.ravel()].mean() > 0.97
    assert d[keep].max() == pytest.approx(0.038, abs=0.004)


def test_dense_reading_on_threads_matches_one_thread(tmp_path):
    """The pairs that see one defect are measured on threads: 1 and 3 threads give the same
    reading, and a pair whose frame is missing is skipped on both."""
    from shapely.geometry import Point

    from roadsurf.detection.dense import DenseContext, measure_defect_dense

    drive, pairs, traj = _scene_and_run(tmp_path)
    missing = dataclasses.replace(pairs[0], frame_b="not_in_the_drive.png")
    pairs = [pairs[0], missing, pairs[0], pairs[0]]
    xy = traj.world_from_cam[0][:2, 3] + pairs[0].points_cam_a_m[:, :2] * [1, -1]
    road = -pairs[0].plane_dist_m < 0.003
    grid = [(k, xy, road) for k in range(len(pairs))]
    poly = Point(0.05, 0.12).buffer(RADIUS_M)

    def reading(workers):
        ctx = DenseContext(drive, pairs, grid, 0.0005, workers)
        return measure_defect_dense(poly, ctx, DenseConfig(), 0.002)

    one, three = reading(1), reading(3)
    assert one is not None and one.max_depth_m == pytest.approx(DEPTH_M, abs=0.003)
    for f in dataclasses.fields(one):
        va, vb = getattr(one, f.name), getattr(three, f.name)
        if isinstance(va, np.ndarray):
            assert np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"), f.name
        else:
            assert va == vb, f.name


def _two_view_with_raster(tmp_path, true: Pothole, raster: Pothole, **kw):
    scene = Scene(potholes=[true])
    drive, pairs, traj = build_two_view(scene, tmp_path / "drive", **kw)
    write_surface(Scene(potholes=[raster]), tmp_path / "run", traj)
    return drive, pairs, traj


def test_narrow_pothole_small_on_the_raster_is_judged_on_its_dense_reading(tmp_path):
    """The raster interpolates the sparse points and smooths: a narrow pothole 40 mm deep
    reads 11 mm there, its part deeper than T_d 17 cm² (< min_area_m2, 20 cm²). Judged on its
    dense reading it is a pothole, measured whole."""
    drive, pairs, traj = _two_view_with_raster(
        tmp_path, Pothole(0.05, 0.12, 0.045, 0.040), Pothole(0.05, 0.12, 0.045, 0.011),
        max_feature_depth_m=0.05,
    )  # fmt: skip
    res = stage.run(DetectionConfig(), drive, pairs, traj, tmp_path / "run")
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m == pytest.approx(0.040, abs=0.004)
    # without a dense reading the raster's judgement stands
    off = DetectionConfig(dense=DenseConfig(enabled=False), overwrite=True)
    assert stage.run(off, drive, pairs, traj, tmp_path / "run").defects == []


def test_region_measured_shallower_than_the_minimum_depth_is_not_reported(tmp_path):
    """The raster's noise lifts a 9 mm dip to 14 mm (above min_depth_m, 10 mm); measured, it
    is 9 mm deep: not a defect, by the same rule."""
    drive, pairs, traj = _two_view_with_raster(
        tmp_path, Pothole(0.05, 0.12, RADIUS_M, 0.009), Pothole(0.05, 0.12, RADIUS_M, 0.014)
    )
    # the sparse points see the whole dip (and flag its middle, deeper than T_d, 8 mm)
    assert (-pairs[0].plane_dist_m).max() > 0.008
    res = stage.run(DetectionConfig(), drive, pairs, traj, tmp_path / "run")
    assert res.defects == []


def test_a_dense_surface_reading_deeper_than_the_tracks_wins(tmp_path):
    """Where surface.tif is the fused dense surface (its DENSE_FOOTPRINT_M tag), its
    supported max also bounds the dense-track reading and the deeper wins (a tilted camera's
    tracks read a floor shallower than the fused views); an interpolated raster's does not."""
    tracks, surface = _depths_before_and_after_the_dense_tag(tmp_path, 0.048)
    assert tracks == pytest.approx(DEPTH_M, abs=0.003)
    assert surface == pytest.approx(0.048, abs=0.003)


def _depths_before_and_after_the_dense_tag(tmp_path, raster_depth_m: float) -> tuple[float, ...]:
    """The one defect's max depth of a two-view run whose tracks read DEPTH_M and whose
    surface.tif reads ``raster_depth_m``: as an interpolated raster, then tagged as the fused
    dense surface (DENSE_FOOTPRINT_M)."""
    import rasterio

    drive, pairs, traj = _two_view_with_raster(
        tmp_path,
        Pothole(0.05, 0.12, RADIUS_M, DEPTH_M),
        Pothole(0.05, 0.12, RADIUS_M, raster_depth_m),
    )
    run = tmp_path / "run"
    depths = []
    for overwrite in (False, True):
        if overwrite:
            with rasterio.open(run / "surface.tif", "r+") as s:
                s.update_tags(DENSE_FOOTPRINT_M="0.009")
        res = stage.run(DetectionConfig(overwrite=overwrite), drive, pairs, traj, run)
        assert len(res.defects) == 1
        depths.append(res.defects[0].max_depth_m)
    return tuple(depths)


def test_tracks_deeper_than_the_dense_surface_supports_do_not_set_the_depth(tmp_path):
    """The tracks and the fused dense surface are two matchers of the same images: tracks
    deeper than the surface supports (by more than max(5 mm, 20 %)) come from failed tracks
    (real photographs: one pair's tracks read 65 mm where the surface read 40 mm), and the
    surface's reading stands; within that tolerance the deeper wins."""
    tracks, surface = _depths_before_and_after_the_dense_tag(tmp_path, 0.026)
    assert tracks == pytest.approx(DEPTH_M, abs=0.003)
    assert surface == pytest.approx(0.026, abs=0.002)


def test_dense_surface_counts_when_the_tracks_cover_too_little_of_the_defect(tmp_path):
    """Tracks that cover too little of the outline (a smooth floor they do not come back
    from) leave the depth to the points and the partial reading; the fused dense surface
    measured the floor, and, as with a full reading, the deeper wins."""
    import rasterio

    drive, pairs, traj = _two_view_with_raster(
        tmp_path, Pothole(0.05, 0.12, RADIUS_M, DEPTH_M), Pothole(0.05, 0.12, RADIUS_M, 0.048)
    )
    run = tmp_path / "run"
    partial = DetectionConfig(dense=DenseConfig(min_coverage=1.0))  # no reading is full
    res = stage.run(partial, drive, pairs, traj, run)
    assert res.defects[0].max_depth_m < 0.046  # the points and the partial tracks
    with rasterio.open(run / "surface.tif", "r+") as s:
        s.update_tags(DENSE_FOOTPRINT_M="0.009")
    partial = dataclasses.replace(partial, overwrite=True)
    res = stage.run(partial, drive, pairs, traj, run)
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m == pytest.approx(0.048, abs=0.003)  # the surface
