"""roadsurf.detection.stage.run end to end on seeded synthetic scenes (tiny images, real files)."""

import dataclasses
import json

import numpy as np
import pytest
import shapely.geometry

from roadsurf.detection import stage
from roadsurf.detection.config import DetectionConfig, RefineConfig
from roadsurf.io.formats import read_csv, read_geojson
from tests.detection.synthetic import REF, Pothole, Scene, Trough, build, write_surface

CFG = DetectionConfig()


def _run(tmp_path, scene, cfg=CFG, **kw):
    drive, pairs, traj = build(scene, tmp_path / "drive", **kw)
    run_dir = tmp_path / "run"
    return stage.run(cfg, drive, pairs, traj, run_dir), run_dir, traj


def test_pothole_of_known_depth_is_measured(tmp_path):
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.030)])
    res, run_dir, _ = _run(tmp_path, scene)
    assert len(res.defects) == 1
    d = res.defects[0]
    assert d.type == "pothole"
    assert d.max_depth_m == pytest.approx(0.030, abs=0.003)
    true_area = np.pi * 0.15**2
    assert d.area_m2 == pytest.approx(true_area, rel=0.2)
    # Paraboloid: mean depth D/2, volume π R² D / 2.
    assert d.mean_depth_m == pytest.approx(0.015, abs=0.003)
    assert d.volume_m3 == pytest.approx(np.pi * 0.15**2 * 0.03 / 2, rel=0.2)
    assert d.length_m == pytest.approx(0.30, rel=0.15) and d.width_m == pytest.approx(
        0.30, rel=0.15
    )
    assert d.severity == "medium"  # ASTM D6433: 25-50 mm deep, 200-450 mm across
    assert set(d.frames) == {"000002.png", "000003.png"}
    assert 0.5 < d.confidence <= 1.0
    frames = {r["filename"]: r for r in read_csv(run_dir / "frames.csv")}
    assert len(frames) == 6
    assert [frames[f"{k:06d}.png"]["defect"] for k in range(6)] == ["0", "0", "1", "1", "0", "0"]
    assert all(r["source"] == "3d" for r in frames.values())


def test_lane_marking_shadow_and_oil_stain_are_not_reported(tmp_path):
    scene = Scene(lane_x_m=-0.3, shadow_x_m=0.25, oil_xy_m=(0.0, 1.0))
    for mode in ("adaptive", "fixed"):
        cfg = dataclasses.replace(CFG, refine=RefineConfig(binarise=mode))
        res, run_dir, _ = _run(tmp_path / mode, scene, cfg=cfg)
        assert res.defects == []
        assert all(f.defect == 0 for f in res.frames)
        assert read_geojson(run_dir / "defects.geojson")["features"] == []


def test_pothole_beside_distractors_is_the_only_defect(tmp_path):
    scene = Scene(
        potholes=[Pothole(-0.1, 1.6, 0.1, 0.025)],
        lane_x_m=0.3,
        shadow_x_m=0.2,
        oil_xy_m=(0.0, 0.6),
    )
    res, _, _ = _run(tmp_path, scene)
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m == pytest.approx(0.025, abs=0.003)


def test_pothole_split_across_two_pairs_is_one_defect(tmp_path):
    scene = Scene(potholes=[Pothole(0.0, 1.0, 0.14, 0.03)])

    def keep(k):
        if k == 2:
            return lambda x, y: y < 1.0  # pair 2 saw the southern half only
        if k == 3:
            return lambda x, y: y >= 1.0  # pair 3 the northern half
        return None

    res, _, _ = _run(tmp_path, scene, keep_per_pair=keep)
    assert len(res.defects) == 1
    d = res.defects[0]
    assert d.area_m2 == pytest.approx(np.pi * 0.14**2, rel=0.25)
    assert d.length_m == pytest.approx(0.28, rel=0.2)


def test_two_potholes_stay_two(tmp_path):
    scene = Scene(potholes=[Pothole(-0.25, 1.0, 0.1, 0.03), Pothole(0.25, 1.0, 0.1, 0.02)])
    res, _, _ = _run(tmp_path, scene)
    assert len(res.defects) == 2
    depths = sorted(d.max_depth_m for d in res.defects)
    assert depths == pytest.approx([0.02, 0.03], abs=0.003)


def test_geojson_is_rfc7946_and_reads_back(tmp_path):
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03), Pothole(-0.2, 1.9, 0.08, 0.02)])
    res, run_dir, _ = _run(tmp_path, scene)
    raw = json.loads((run_dir / "defects.geojson").read_text())
    fc = read_geojson(run_dir / "defects.geojson")  # validates lon/lat and closed rings
    assert fc == raw and len(fc["features"]) == 2
    keys = {"id", "type", "severity", "max_depth_m", "mean_depth_m", "area_m2", "volume_m3"}
    keys |= {"length_m", "width_m", "confidence", "frames"}
    for f in fc["features"]:
        assert keys <= set(f["properties"])
        ring = f["geometry"]["coordinates"][0]
        assert ring[0] == ring[-1]
        poly = shapely.geometry.shape(f["geometry"])
        assert poly.is_valid and poly.geom_type == "Polygon"
        lon, lat = poly.centroid.x, poly.centroid.y
        assert abs(lon - REF.lon_deg) < 1e-4 and abs(lat - REF.lat_deg) < 1e-4
        assert poly.contains(
            shapely.geometry.Point(f["properties"]["centroid_lon"], f["properties"]["centroid_lat"])
        )
    # detection.json (the resume record) holds the same lon/lat as the GeoJSON
    saved = json.loads((run_dir / "detection.json").read_text())["defects"]
    for f, d in zip(fc["features"], saved, strict=True):
        assert d["centroid_lon"] == pytest.approx(f["properties"]["centroid_lon"], abs=1e-9)
        assert d["centroid_lat"] == pytest.approx(f["properties"]["centroid_lat"], abs=1e-9)
    # as a GIS reads it: GDAL's GeoJSON driver, WGS84 lon/lat
    import pyogrio

    info = pyogrio.read_info(run_dir / "defects.geojson")
    assert info["crs"] == "EPSG:4326" and info["features"] == 2
    rows = read_csv(run_dir / "defects.csv")
    assert [int(r["id"]) for r in rows] == [1, 2]
    assert float(rows[0]["centroid_e_m"]) > 100000  # UTM easting
    assert {r["crs_of_e_n"] for r in rows} == {"EPSG:32617"}
    assert rows[0]["frames"].split(";") == res.defects[0].frames


def test_no_gps_writes_local_coordinates(tmp_path, caplog):
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03)])
    res, run_dir, _ = _run(tmp_path, scene, georeferenced=False)
    assert not res.georeferenced and len(res.defects) == 1
    fc = json.loads((run_dir / "defects.geojson").read_text())
    assert "never lon/lat" in fc["properties"]["coordinates"]
    # a GIS must not take the local metres for lon/lat: GDAL reads the legacy crs member as a
    # local engineering frame in metres (without it, EPSG:4326)
    import pyogrio
    import pyproj

    crs = pyproj.CRS.from_user_input(pyogrio.read_info(run_dir / "defects.geojson")["crs"])
    assert crs.type_name == "Engineering CRS" and not crs.is_geographic
    assert {a.unit_name for a in crs.axis_info} == {"metre"}
    row = read_csv(run_dir / "defects.csv")[0]
    assert row["centroid_lon"] == "" and row["centroid_lat"] == ""
    assert row["crs_of_e_n"] == "local (no GPS)"
    assert float(row["centroid_e_m"]) == pytest.approx(0.1, abs=0.02)
    assert float(row["centroid_n_m"]) == pytest.approx(1.0, abs=0.02)


def test_surface_raster_path_measures_depth_area_and_types(tmp_path):
    scene = Scene(
        potholes=[Pothole(0.15, 0.9, 0.15, 0.045)],
        troughs=[
            Trough(-0.3, 0.2, -0.3, 1.9, 0.25, 0.018),  # rut: long, wide, shallow
            Trough(0.2, 1.5, 0.35, 2.1, 0.03, 0.012),  # crack: narrow
        ],
    )
    drive, pairs, traj = build(scene, tmp_path / "drive")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    write_surface(scene, run_dir, traj)
    res = stage.run(CFG, drive, pairs, traj, run_dir)
    assert res.surface_source == "surface.tif"
    by_type = {d.type: d for d in res.defects}
    assert sorted(by_type) == ["crack", "pothole", "rut"], res.table()
    p = by_type["pothole"]
    assert p.max_depth_m == pytest.approx(0.045, abs=0.002)
    assert p.area_m2 == pytest.approx(np.pi * 0.15**2, rel=0.12)
    assert p.severity == "medium"  # 25-50 mm, 200-450 mm
    r = by_type["rut"]
    assert r.length_m == pytest.approx(1.7, rel=0.1)
    assert r.max_depth_m == pytest.approx(0.018, abs=0.002)
    assert r.severity == "medium"  # ASTM D6433 rutting 13-25 mm


def test_resume_and_overwrite(tmp_path):
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03)])
    drive, pairs, traj = build(scene, tmp_path / "drive")
    run_dir = tmp_path / "run"
    first = stage.run(CFG, drive, pairs, traj, run_dir)
    stamp = (run_dir / "detection.json").stat().st_mtime_ns
    again = stage.run(CFG, drive, pairs, traj, run_dir)
    assert (run_dir / "detection.json").stat().st_mtime_ns == stamp  # read back, not rewritten
    assert [d.area_m2 for d in again.defects] == pytest.approx(
        [d.area_m2 for d in first.defects], rel=1e-4
    )
    assert again.table() == first.table()
    stage.run(dataclasses.replace(CFG, overwrite=True), drive, pairs, traj, run_dir)
    assert (run_dir / "detection.json").stat().st_mtime_ns != stamp


def test_a_stopped_rewrite_leaves_no_record_and_garbage_is_redetected(tmp_path, monkeypatch):
    """detection.json goes before the outputs are rewritten (a rewrite stopped half way left
    the old record beside 6 of 7 defects and a third of the masks, and a resume reused them);
    a detection.json that is not an object is detected again (it stopped with a traceback)."""
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03)])
    drive, pairs, traj = build(scene, tmp_path / "drive")
    run_dir = tmp_path / "run"
    first = stage.run(CFG, drive, pairs, traj, run_dir)
    (run_dir / "detection.json").write_text("[1, 2]")
    assert stage.run(CFG, drive, pairs, traj, run_dir).table() == first.table()

    def stopped(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(stage, "_detect", stopped)
    other = dataclasses.replace(CFG, fusion_threshold=0.9)
    with pytest.raises(KeyboardInterrupt):
        stage.run(other, drive, pairs, traj, run_dir)
    assert not (run_dir / "detection.json").exists()


def test_cnn_probabilities_are_fused(tmp_path):
    """frames.csv follows detection.classifier.fusion applied to the 3D labels (Fig. 5.6)."""
    from roadsurf.detection.classifier.fusion import fuse_frames

    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03)])
    drive, pairs, traj = build(scene, tmp_path / "drive")
    only_3d = stage.run(CFG, drive, pairs, traj, tmp_path / "run3d")
    labels_3d = {f.filename: bool(f.defect) for f in only_3d.frames}
    probs = {"000000.png": 0.01, "000001.png": 0.6, "000002.png": 0.99, "000005.png": 0.01}
    res = stage.run(CFG, drive, pairs, traj, tmp_path / "run", frame_probs=probs)
    names = [f.filename for f in drive.frames]
    want = fuse_frames(probs, labels_3d, names, CFG.fusion_threshold)
    by = {f.filename: f for f in res.frames}
    for fn in names:
        assert (by[fn].defect, by[fn].source) == (int(want[fn].defect), want[fn].source), fn
    assert by["000002.png"].source == "fused" and by["000002.png"].defect == 1
    assert by["000001.png"].source == "3d" and by["000001.png"].defect == 0
    rows = read_csv(tmp_path / "run" / "frames.csv")
    assert {r["source"] for r in rows} >= {"3d", "fused"}


def test_failed_pairs_are_skipped(tmp_path):
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03)])
    drive, pairs, traj = build(scene, tmp_path / "drive")
    pairs[0] = dataclasses.replace(
        pairs[0], status="too_few_matches", points_cam_a_m=np.zeros((0, 3))
    )
    res = stage.run(CFG, drive, pairs, traj, tmp_path / "run")
    assert len(res.defects) == 1


def test_pair_level_frame_decision(tmp_path):
    """The dissertation's per-pair decision (frame_label: pair) sees the pothole in frames 2, 3."""
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03)], shadow_x_m=0.3, lane_x_m=-0.3)
    cfg = dataclasses.replace(CFG, frame_label="pair")
    res, _, _ = _run(tmp_path, scene, cfg=cfg)
    labels = [f.defect for f in res.frames]
    assert labels[2] == labels[3] == 1
    assert labels[0] == 0 and labels[5] == 0


def test_map_points_fallback_when_no_raster(tmp_path):
    """Without surface.tif the stage rasterises RUN/map_points.npz (mapping's fused points)."""
    scene = Scene(potholes=[Pothole(0.0, 1.2, 0.12, 0.035)], shadow_x_m=0.2)
    drive, pairs, traj = build(scene, tmp_path / "drive")
    rng = np.random.default_rng(5)
    xy = np.column_stack([rng.uniform(-0.5, 0.5, 40000), rng.uniform(-0.4, 2.4, 40000)])
    res_m = -scene.depth(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.0007, len(xy))
    run_dir = tmp_path / "run"
    _write_map_points(run_dir, xy, res_m)
    res = stage.run(CFG, drive, pairs, traj, run_dir)
    assert res.surface_source == "map_points.npz"
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m == pytest.approx(0.035, abs=0.004)
    assert res.defects[0].area_m2 == pytest.approx(np.pi * 0.12**2, rel=0.2)


def test_max_depth_from_pairs_not_the_pose_smeared_map(tmp_path):
    """A trajectory error smears the fused map's copy of a pothole (two copies 6 cm apart,
    averaged: 26 mm instead of 35 mm deep); each pair still sees it in its own frame, and the
    max depth is measured there."""
    scene = Scene(potholes=[Pothole(0.0, 1.2, 0.12, 0.035)])
    drive, pairs, traj = build(scene, tmp_path / "drive")
    rng = np.random.default_rng(7)
    xy = np.column_stack([rng.uniform(-0.5, 0.5, 40000), rng.uniform(-0.4, 2.4, 40000)])
    smeared = 0.5 * (
        scene.depth(xy[:, 0] - 0.06, xy[:, 1]) + scene.depth(xy[:, 0] + 0.06, xy[:, 1])
    )
    res_m = -smeared + rng.normal(0, 0.0007, len(xy))
    run_dir = tmp_path / "run"
    _write_map_points(run_dir, xy, res_m)
    res = stage.run(CFG, drive, pairs, traj, run_dir)
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m == pytest.approx(0.035, abs=0.003)


def test_map_depth_the_pairs_do_not_support_is_not_reported(tmp_path):
    """Two stretches of road fused into one place (a segment placed by a guess over another,
    15 cm lower): the map's points read the pothole 150 mm deep, every pair that saw it reads
    35 mm in its own frame. The map's points are the pairs' points placed by the trajectory,
    so the depth the pairs do not see is the placement's, and the pairs' reading stands."""
    scene = Scene(potholes=[Pothole(0.0, 1.2, 0.12, 0.035)])
    drive, pairs, traj = build(scene, tmp_path / "drive")
    rng = np.random.default_rng(7)
    xy = np.column_stack([rng.uniform(-0.5, 0.5, 40000), rng.uniform(-0.4, 2.4, 40000)])
    res_m = -scene.depth(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.0007, len(xy))
    other = np.column_stack([rng.uniform(-0.04, 0.04, 300), rng.uniform(1.16, 1.24, 300)])
    xy = np.vstack([xy, other])
    res_m = np.concatenate([res_m, np.full(len(other), -0.15) + rng.normal(0, 0.0007, 300)])
    run_dir = tmp_path / "run"
    _write_map_points(run_dir, xy, res_m)
    res = stage.run(CFG, drive, pairs, traj, run_dir)
    assert len(res.defects) == 1
    assert res.defects[0].max_depth_m == pytest.approx(0.035, abs=0.004)


def test_defect_deeper_than_the_plane_fit_accepts_is_not_reported(tmp_path):
    """A failed reconstruction (a pair with the wrong plane) maps metres-deep "defects"; what
    the plane fit itself calls a mismatch (deeper than plane.max_depth_m) is not a defect. Here
    the bound is lowered to 20 mm below a 35 mm pothole to show the rule on a clean scene."""
    scene = Scene(potholes=[Pothole(0.0, 1.2, 0.12, 0.035)])
    res, _, _ = _run(tmp_path / "a", scene)
    assert len(res.defects) == 1
    low = dataclasses.replace(CFG, plane=dataclasses.replace(CFG.plane, max_depth_m=0.02))
    res, _, _ = _run(tmp_path / "b", scene, cfg=low)
    assert res.defects == []


def _write_map_points(run_dir, xy, res_m):
    """RUN/map_points.npz as mapping writes it (grid-frame xy == ENU here, z = residual)."""
    from roadsurf.core.atomic import write_npz_atomic

    write_npz_atomic(
        run_dir / "map_points.npz",
        xyz=np.column_stack([xy, res_m]),
        rgb=np.zeros((len(xy), 3), np.uint8),
        residual_m=res_m,
        frame_index=np.zeros(len(xy), int),
    )


def test_pairs_analysed_by_threads_match_one_thread(tmp_path):
    """analyse_pairs on 1 and 3 threads: the same refined points, distances, scores, cracks and
    mask files, in pair order; an unreadable frame leaves its pairs to 3D only on both."""
    from roadsurf.detection.pairs import PairDefects, analyse_pairs

    scene = Scene(
        potholes=[Pothole(0.1, 1.0, 0.15, 0.030), Pothole(-0.1, 2.0, 0.1, 0.02)],
        troughs=[Trough(-0.2, 0.4, -0.2, 2.6, 0.3, 0.012)],
        shadow_x_m=0.3,
    )
    drive, pairs, _ = build(scene, tmp_path / "drive", n_frames=8)
    (tmp_path / "drive" / "frames" / "000005.png").write_bytes(b"not a png")

    def analyse(workers: int) -> tuple[dict[int, PairDefects], dict[str, bytes]]:
        masks = tmp_path / f"masks{workers}"
        masks.mkdir()
        out = analyse_pairs(dataclasses.replace(CFG, pair_workers=workers), drive, pairs, masks)
        return out, {p.name: p.read_bytes() for p in sorted(masks.iterdir())}

    one, masks1 = analyse(1)
    three, masks3 = analyse(3)
    assert list(one) == list(three) == sorted(one) and len(one) == len(pairs)
    assert masks1 == masks3 and len(masks1) >= 4
    for k in one:
        a, b = one[k], three[k]
        assert np.array_equal(a.refined, b.refined) and np.array_equal(a.dist_m, b.dist_m)
        assert (a.score, a.threshold_m, a.deep_area_m2) == (b.score, b.threshold_m, b.deep_area_m2)
        assert (a.cracks is None) == (b.cracks is None)
        if a.cracks is not None:
            for f in dataclasses.fields(a.cracks):
                va, vb = getattr(a.cracks, f.name), getattr(b.cracks, f.name)
                if va is None or vb is None:
                    assert va is None and vb is None, f.name
                    continue
                va, vb = np.asarray(va), np.asarray(vb)  # NaN: a share not measured
                assert np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"), f.name
    assert any(one[k].refined.any() for k in one)


def test_the_signature_holds_the_detection_version(tmp_path, monkeypatch):
    """A resumed run re-detects after detection changed its outputs (DETECTION_VERSION)."""
    from roadsurf.detection import output
    from roadsurf.mapping.types import Trajectory

    traj = Trajectory(["a.png"], np.zeros(1, int), np.zeros(1), np.eye(4)[None], ["gps"], None)
    one = output.signature(DetectionConfig(), [], traj, tmp_path, None)
    assert output.signature(DetectionConfig(), [], traj, tmp_path, None) == one
    monkeypatch.setattr(output, "DETECTION_VERSION", output.DETECTION_VERSION + 1)
    assert output.signature(DetectionConfig(), [], traj, tmp_path, None) != one
