"""The run is logged to a real .rrd and read back with Rerun's own chunk API."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from roadsurf.core.geometry import ExportFrame
from roadsurf.viewer.api import save_rrd
from roadsurf.viewer.inspect import component_values, summarize_rrd
from roadsurf.viewer.profile import depth_profile
from roadsurf.viewer.runfolder import enu_from_crs, load_run
from tests.viewer.synthetic_run import REF, SyntheticRun, make_synthetic_run


def test_rrd_holds_cloud_defects_trajectory_map_and_images(
    synthetic_run: SyntheticRun, saved_rrd: Path
) -> None:
    exp = synthetic_run.expected
    s = summarize_rrd(saved_rrd)
    assert s.n_recordings == 1 and s.n_blueprints == 1  # the layout travels with the file
    assert {"frame", "time"} <= s.timelines

    # point cloud, every point, coloured
    assert s.instances("/world/cloud", "Points3D:positions") == exp["cloud_points"]
    assert s.instances("/world/cloud", "Points3D:colors") == exp["cloud_points"]
    # defects: outlines + boxes in 3D, labelled
    assert s.instances("/world/defects", "LineStrips3D:strips") == exp["defects"]
    assert s.instances("/world/defect_boxes", "Boxes3D:centers") == exp["defects"]
    # trajectory, current camera pose per frame, at least one static frustum
    assert s.instances("/world/trajectory", "LineStrips3D:strips") == 1
    assert s.rows("/world/camera", "Transform3D:translation") == exp["frames"]
    assert s.rows("/world/camera", "Pinhole:image_from_camera") == 1
    assert len(s.under("/world/frusta")) >= 1
    # map view entities
    assert s.instances("/map/gps_track", "GeoLineStrings:line_strings") == 1
    assert s.instances("/map/gps_fixes", "GeoPoints:positions") == exp["gps_fixes"]
    assert s.instances("/map/trajectory", "GeoLineStrings:line_strings") == 1
    assert s.instances("/map/defects", "GeoPoints:positions") == exp["defects"]
    # images on the timeline with their overlays, mosaic, mask
    assert s.rows("/world/camera/image", "EncodedImage:blob") == exp["frames"]
    assert s.instances("/world/camera/image/matches", "Points2D:positions") == (
        exp["pairs_ok"] * exp["matches_per_pair"]
    )
    assert s.instances("/world/camera/image/rejected", "Points2D:positions") == (
        exp["pairs_ok"] * exp["rejected_per_pair"]
    )
    assert s.instances("/world/camera/image/defect_points", "Points2D:positions") == (
        exp["pairs_ok"] * exp["deep_points_per_pair"]
    )
    assert s.rows("/world/camera/image/mask", "SegmentationImage:buffer") == 1
    assert s.rows("/mosaic/image", "Image:buffer") == 1
    assert s.rows("/surface/image", "Image:buffer") == 1
    assert s.rows("/frames/p_defect", "Scalars:scalars") == exp["frames"]
    assert s.rows("/log", "TextLog:text") == 1  # the one failed pair
    assert len(s.under("/profiles")) == exp["defects"]


def test_rrd_values_are_local_enu_and_georeferenced(saved_rrd: Path) -> None:
    cloud = np.array(component_values(saved_rrd, "/world/cloud", "Points3D:positions")[0])
    # the PLY is in UTM; the viewer must draw local ENU metres (float32-safe)
    assert np.abs(cloud[:, :2]).max() < 2.0
    assert cloud[:, 0].min() == np.float32(-0.3) or abs(cloud[:, 0].min() + 0.3) < 1e-4
    assert -0.032 < cloud[:, 2].min() < -0.027  # the 30 mm pothole floor, not the UTM height
    latlon = np.array(component_values(saved_rrd, "/map/defects", "GeoPoints:positions")[0])
    ef = ExportFrame.for_reference(REF)
    pothole = ef.lonlat_from_enu(np.array([[0.05, 0.35, 0.0]]))[0]
    # defects are sorted by severity: the medium pothole comes first
    assert abs(latlon[0, 0] - pothole[1]) < 2e-7 and abs(latlon[0, 1] - pothole[0]) < 2e-7
    labels = component_values(saved_rrd, "/world/defects", "LineStrips3D:labels")[0]
    assert labels[0].startswith("#1 pothole 30 mm") and labels[0].endswith("medium")
    assert "crack" in labels[1] and "low" in labels[1]


def test_run_without_gps_or_defects_still_records(tmp_path: Path) -> None:
    syn = make_synthetic_run(tmp_path, gps=False, defects=False, n_frames=4)
    res = save_rrd(syn.run)
    s = summarize_rrd(res.rrd)
    assert s.instances("/world/cloud", "Points3D:positions") == syn.expected["cloud_points"]
    assert s.rows("/world/camera/image", "EncodedImage:blob") == 4
    assert not s.under("/map")  # nothing to put on a map without GPS
    assert not s.has("/world/defects")


def test_run_folder_without_drive_or_pairs(tmp_path: Path, synthetic_run: SyntheticRun) -> None:
    """A copied run folder whose drive is gone: 3D and map still load, images are left out."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(synthetic_run.run, run, ignore=shutil.ignore_patterns("pairs", "*.rrd"))
    report = (
        (run / "report.json")
        .read_text()
        .replace(str(synthetic_run.drive.resolve()), "/nonexistent/drive")
    )
    (run / "report.json").write_text(report)
    res = save_rrd(run)
    assert any("drive" in m for m in res.missing) and "pairs/" in res.missing
    s = summarize_rrd(res.rrd)
    assert s.has("/world/cloud") and s.has("/map/defects") and s.has("/world/trajectory")
    assert s.rows("/world/camera/image", "EncodedImage:blob") == 0
    assert s.rows("/world/camera", "Transform3D:translation") == synthetic_run.expected["frames"]


def test_cloud_from_utm_is_exact_enu() -> None:
    ef = ExportFrame.for_reference(REF)
    enu = np.array([[0.0, 0.0, 0.0], [12.3, -45.6, -0.012], [-100.0, 250.0, 1.5]])
    back = enu_from_crs(ef.utm_from_enu(enu), ef.crs, REF)
    assert np.abs(back - enu).max() < 1e-6


@pytest.mark.parametrize("source", ["surface", "cloud"])
def test_depth_profile_finds_the_pothole_floor(synthetic_run: SyntheticRun, source: str) -> None:
    data = load_run(synthetic_run.run, with_pairs=False)
    if source == "cloud":
        data.surface = None  # profile from the cloud points instead of surface.tif
    pothole = next(d for d in data.defects if d.type == "pothole")
    dist, res = depth_profile(data, pothole, n_samples=32)
    assert dist.shape == res.shape == (32,)
    k = int(np.nanargmin(res))
    assert -0.032 < res[k] < -0.024  # near the 30 mm floor
    mid = 0.5 * (dist[0] + dist[-1])
    assert abs(dist[k] - mid) < 0.03  # at the middle of the long axis
    assert math.isclose(float(np.nanmax(res)), 0.0, abs_tol=0.003)  # road beyond the rim


def test_map_defects_are_projected_into_the_frames(saved_rrd: Path) -> None:
    """The pothole (E 0.05, N 0.35) seen by a camera 0.5 m up at N = 0.1 i, heading north:
    u = cx + fx * 0.05 / 0.5 = 95 px, v = cy - fy * (0.35 - 0.1 i) / 0.5."""
    rows = component_values(saved_rrd, "/world/camera/image/defect_outlines", "LineStrips2D:strips")
    labels = component_values(
        saved_rrd, "/world/camera/image/defect_outlines", "LineStrips2D:labels"
    )
    centres = [
        np.array(strip)[:-1].mean(axis=0)
        for row, lab in zip(rows, labels, strict=True)
        for strip, text in zip(row, lab, strict=True)
        if "pothole" in text
    ]
    assert len(centres) >= 4
    vs = sorted(round(float(c[1])) for c in centres)
    for i in (2, 3, 4, 5):
        v = 60.0 - 150.0 * (0.35 - 0.1 * i) / 0.5
        assert any(abs(x - v) <= 1 for x in vs), (v, vs)
    assert all(abs(float(c[0]) - 95.0) < 1.0 for c in centres)


def test_defects_without_gps_are_local_enu_metres(tmp_path: Path) -> None:
    """Without GPS detection writes the GeoJSON layout with local ENU metres (not lon/lat)."""
    import json

    syn = make_synthetic_run(tmp_path, gps=False, defects=True, n_frames=4)
    fc = json.loads((syn.run / "defects.geojson").read_text())
    for f in fc["features"]:  # move them far enough that lon/lat validation would reject them
        f["geometry"]["coordinates"] = [
            [[x + 250.0, y - 120.0] for x, y in ring] for ring in f["geometry"]["coordinates"]
        ]
    (syn.run / "defects.geojson").write_text(json.dumps(fc))
    data = load_run(syn.run, with_pairs=False)
    assert len(data.defects) == 2
    assert all(d.ring_lonlat is None for d in data.defects)
    pothole = next(d for d in data.defects if d.type == "pothole")
    assert np.allclose(pothole.centroid_enu_m, [250.05, -119.65], atol=1e-6)
    s = summarize_rrd(save_rrd(syn.run).rrd)
    assert s.instances("/world/defects", "LineStrips3D:strips") == 2
    assert not s.under("/map")


@pytest.mark.parametrize("gps", [True, False])
def test_defect_centroids_are_the_stored_ones(tmp_path: Path, gps: bool) -> None:
    """The viewer (and the HTML report) place a defect at the centroid detection stored (what
    defects.csv says), not at its outline vertices' mean: put it on the first vertex."""
    import json

    syn = make_synthetic_run(tmp_path, gps=gps, defects=True, n_frames=4)
    fc = json.loads((syn.run / "defects.geojson").read_text())
    keys = ("centroid_lon", "centroid_lat") if gps else ("centroid_e_m", "centroid_n_m")
    for f in fc["features"]:
        first = f["geometry"]["coordinates"][0][0]
        f["properties"].update(dict(zip(keys, first[:2], strict=True)))
    (syn.run / "defects.geojson").write_text(json.dumps(fc))
    data = load_run(syn.run, with_pairs=False)
    assert len(data.defects) == 2
    for d in data.defects:
        assert np.allclose(d.centroid_enu_m, d.ring_enu_m[0], atol=1e-6)
        assert not np.allclose(d.centroid_enu_m, d.ring_enu_m[:-1].mean(axis=0), atol=1e-3)
