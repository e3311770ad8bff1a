"""Issue 31: implausible inputs are named with figures (camera height vs the GPS baseline,
swapped lat/lon, a static receiver, GPS σ inflation), a run in which no pair reconstructs stops
with one line, a run folder of another drive is refused, and heights name their datum."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from roadsurf.core.errors import ConfigError, RoadsurfError
from roadsurf.mapping import poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.datum import GPS_DATUM_DEFAULT, LOCAL_DATUM, vertical_datum
from roadsurf.pipeline.run_checks import (
    RUN_JSON,
    NoReconstructionError,
    check_reconstruction,
    claim_run_folder,
)
from roadsurf.reconstruction.config import ReconstructionConfig
from tests.mapping.synth import failed_pair, make_synthetic, write_drive


def _rtk(n: int = 80, height_m: float = 1.0, scale: float = 1.0, hdop: float = 0.04, **kw):
    """RTK-like GPS (σ 2 cm; HDOP 0.04 states it) and pairs whose metric scale is ``scale`` ×
    the truth, as a camera.yaml ``height_m`` of ``height_m`` × ``scale`` gives (α = h / d_c)."""
    syn = make_synthetic(n=n, seed=4, gps_hz=5.0, hdop=hdop, **kw)
    syn.drive.camera = dataclasses.replace(syn.drive.camera, height_m=height_m * scale)
    pairs = []
    for p in syn.pairs:
        q = copy.copy(p)
        q.t_b_from_a_m, q.points_cam_a_m = p.t_b_from_a_m * scale, p.points_cam_a_m * scale
        pairs.append(q)
    return syn, pairs


def test_clean_drive_raises_no_plausibility_warning() -> None:
    syn, pairs = _rtk()
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    assert rep.warnings == []
    assert abs(rep.checks["gps_over_visual"]["ratio"] - 1) < 0.02


def test_camera_height_20_percent_wrong_warns_with_the_true_value() -> None:
    syn, pairs = _rtk(scale=1.2)  # height_m 1.20 typed for a 1.00 m camera
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    msg = [w for w in rep.warnings if w.startswith("camera.yaml height_m 1.20 m")]
    assert len(msg) == 1, rep.warnings
    assert abs(rep.checks["height_implied_m"] - 1.0) < 0.02
    assert "the data imply 1.00 m" in msg[0]
    # the pose graph's σ inflation is reported too, with its factor
    assert any("inflated the GPS sigma" in w for w in rep.warnings)


def test_swapped_lat_lon_are_named() -> None:
    syn, pairs = _rtk()
    g = syn.drive.gps
    syn.drive.gps = dataclasses.replace(g, lat_deg=g.lon_deg, lon_deg=g.lat_deg)
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    assert any(w.startswith("lat/lon look swapped in gps.csv") for w in rep.warnings)
    assert rep.checks["gps_hypothesis"] == "lat/lon look swapped"
    assert not any(w.startswith("camera.yaml") for w in rep.warnings)


def test_static_receiver_and_sigma_inflation_are_named() -> None:
    syn, pairs = _rtk()
    g = syn.drive.gps
    syn.drive.gps = dataclasses.replace(
        g, lat_deg=np.full(len(g), g.lat_deg[0]), lon_deg=np.full(len(g), g.lon_deg[0])
    )
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    static = [w for w in rep.warnings if w.startswith("GPS looks static over frames")]
    assert static and "while vision travels" in static[0]
    inflated = [w for w in rep.warnings if "inflated the GPS sigma" in w]
    assert inflated and f"{rep.gps_sigma_scale:.1f}x" in inflated[0]


def test_no_pair_reconstructed_is_an_error_naming_the_reasons(tmp_path: Path) -> None:
    from roadsurf.pipeline.run import run_drive

    syn = make_synthetic(n=4, seed=1)
    drive = write_drive(syn, tmp_path / "drive")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("reconstruction:\n  min_matches: 100000\n  workers: 1\n")
    with pytest.raises(NoReconstructionError, match=r"0 of 3 pairs ok \(\w+: 3\)") as e:
        run_drive(drive, tmp_path / "run", config_path=cfg)
    assert isinstance(e.value, RoadsurfError)  # the CLI exits 2 with this one line
    assert "reconstruction.min_matches (100000)" in str(e.value)
    assert not (tmp_path / "run" / "frames.csv").exists()  # no "no defect" labels


def test_camera_height_in_cm_is_named_when_nothing_reconstructs() -> None:
    syn = make_synthetic(n=4, seed=1)
    syn.drive.camera = dataclasses.replace(syn.drive.camera, height_m=110.0)
    pairs = [failed_pair(i, "scale_failed") for i in range(3)]
    with pytest.raises(NoReconstructionError, match=r"height_m in camera.yaml \(110 m"):
        check_reconstruction(pairs, syn.drive, ReconstructionConfig(), Path("RUN"))
    check_reconstruction([], syn.drive, ReconstructionConfig(), Path("RUN"))  # nothing tried


def test_a_rolling_shutter_is_named_when_nothing_reconstructs() -> None:
    """20 ms of readout at 15 m/s and 30 fps leaves 14 % of the road in common: the stop names
    the readout, not only the overlap."""
    syn = make_synthetic(n=4, seed=1)
    syn.drive.camera = dataclasses.replace(syn.drive.camera, readout_s=0.02)
    pairs = [failed_pair(i, "no_overlap") for i in range(3)]
    with pytest.raises(NoReconstructionError, match=r"rolling shutter \(camera.yaml readout_s 20"):
        check_reconstruction(pairs, syn.drive, ReconstructionConfig(), Path("RUN"))


def test_dark_frames_are_named_when_nothing_reconstructs(tmp_path: Path) -> None:
    """Frames too dark for features (median 12 DN) fail as too few matches; the error names
    the exposure first, with the measured brightness, not only the overlap and min_matches."""
    import cv2

    syn = make_synthetic(n=4, seed=1)
    drive_dir = write_drive(syn, tmp_path / "drive")
    pairs = [failed_pair(i, "too_few_matches") for i in range(3)]
    from roadsurf.io.drive import load_drive

    drive = load_drive(drive_dir)
    check = r"Check the exposure: the frames are very dark \(median 12 DN"
    for f in drive.frames:  # the same scenes, 12 DN on average
        img = cv2.imread(str(f.path), cv2.IMREAD_GRAYSCALE).astype(float)
        cv2.imwrite(str(f.path), np.clip(img * 12.0 / np.median(img), 0, 255).astype(np.uint8))
    with pytest.raises(NoReconstructionError, match=check):
        check_reconstruction(pairs, drive, ReconstructionConfig(), Path("RUN"))
    for f in drive.frames:  # well exposed: no such hint
        img = cv2.imread(str(f.path), cv2.IMREAD_GRAYSCALE).astype(float)
        cv2.imwrite(str(f.path), np.clip(img * 10.0, 0, 255).astype(np.uint8))
    with pytest.raises(NoReconstructionError) as e:
        check_reconstruction(pairs, drive, ReconstructionConfig(), Path("RUN"))
    assert "exposure" not in str(e.value)


def test_no_motion_pairs_are_not_reported_as_failures(tmp_path: Path) -> None:
    from roadsurf.pipeline.run_checks import pair_failures_warning
    from roadsurf.reconstruction.types import STATUS_NO_MOTION

    syn = make_synthetic(n=11, seed=1)
    still = [failed_pair(i, STATUS_NO_MOTION) for i in range(2, 8)]
    assert pair_failures_warning(syn.pairs[:2] + still + syn.pairs[8:], tmp_path) is None
    broken = [failed_pair(i) for i in range(2, 8)]
    assert "6 of 10 pairs failed" in str(
        pair_failures_warning(syn.pairs[:2] + broken + syn.pairs[8:], tmp_path)
    )


def test_run_folder_of_another_drive_is_refused(tmp_path: Path) -> None:
    from roadsurf.pipeline.run import run_drive

    a = write_drive(make_synthetic(n=3, seed=1), tmp_path / "A")
    b = write_drive(make_synthetic(n=3, seed=2), tmp_path / "B")
    out = tmp_path / "run"
    out.mkdir()
    claim_run_folder(a, out, overwrite=False)
    assert (out / RUN_JSON).is_file()
    claim_run_folder(a, out, overwrite=False)  # the same drive resumes
    with pytest.raises(ConfigError, match="another drive") as e:
        run_drive(b, out)
    assert str(a.resolve()) in str(e.value) and str(b.resolve()) in str(e.value)
    assert "--overwrite" in str(e.value)
    claim_run_folder(b, out, overwrite=True)  # --overwrite takes the folder
    with pytest.raises(ConfigError, match="another drive"):
        claim_run_folder(a, out, overwrite=False)


def test_run_folder_of_an_older_run_is_checked_by_its_report(tmp_path: Path) -> None:
    a = write_drive(make_synthetic(n=3, seed=1), tmp_path / "A")
    out = tmp_path / "run"
    out.mkdir()
    (out / "report.json").write_text('{"drive": "/somewhere/else"}')
    with pytest.raises(ConfigError, match="/somewhere/else"):
        claim_run_folder(a, out, overwrite=False)


def test_heights_name_their_vertical_datum(tmp_path: Path) -> None:
    from plyfile import PlyData

    from roadsurf.io.formats import read_geojson
    from roadsurf.mapping.export import write_cloud_ply, write_trajectory_geojson

    syn = make_synthetic(n=20, seed=3)
    cfg = MappingConfig()
    assert vertical_datum(cfg, syn.drive) == GPS_DATUM_DEFAULT
    assert vertical_datum(cfg, make_synthetic(n=5, with_gps=False).drive) == LOCAL_DATUM
    traj, rep = poses.estimate_trajectory(cfg, syn.drive, syn.pairs)
    assert rep.vertical_datum == GPS_DATUM_DEFAULT
    ef = traj.export_frame
    xyz = traj.positions_enu_m
    ply = write_cloud_ply(
        tmp_path / "c.ply", xyz, np.zeros((len(xyz), 3)), np.zeros(len(xyz)), ef,
        vertical_datum=rep.vertical_datum,
    )  # fmt: skip
    comments = PlyData.read(str(ply)).comments
    assert f"vertical_datum: {GPS_DATUM_DEFAULT}" in comments and f"crs: {ef.crs}" in comments
    gj = write_trajectory_geojson(
        tmp_path / "t.geojson", traj, syn.drive, vertical_datum=rep.vertical_datum
    )
    assert read_geojson(gj)["properties"]["vertical_datum"] == GPS_DATUM_DEFAULT
    # the same folder run again without GPS: no lon/lat of the earlier run is left behind
    local = make_synthetic(n=5, with_gps=False)
    traj_local, _ = poses.estimate_trajectory(cfg, local.drive, local.pairs)
    assert traj_local.export_frame is None
    assert write_trajectory_geojson(tmp_path / "t.geojson", traj_local, local.drive) is None
    assert not (tmp_path / "t.geojson").exists()


# 0.75 s of frames, fixes 1.5 s either side (like the fault battery's 12-frame drive); RTK fixes
# logged with a consumer HDOP (stated σ 0.4 m)
SHORT = {"n": 16, "hdop": 0.8, "gps_margin_s": 1.5}


def test_short_drive_with_understated_gps_still_checks_the_height() -> None:
    """The fault battery's 12-frame drive: the stated σ (0.4 m) makes every chord too short to
    judge; the fixes' own scatter (2 cm) does not."""
    syn, pairs = _rtk(scale=1.2, **SHORT)
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    assert any(w.startswith("camera.yaml height_m 1.20 m") for w in rep.warnings), rep.warnings
    syn, pairs = _rtk(**SHORT)
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    assert rep.warnings == []


def test_short_drive_swapped_and_static_are_named() -> None:
    syn, pairs = _rtk(**SHORT)
    g = syn.drive.gps
    syn.drive.gps = dataclasses.replace(g, lat_deg=g.lon_deg, lon_deg=g.lat_deg)
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    assert any(w.startswith("lat/lon look swapped") for w in rep.warnings), rep.warnings
    assert not any(w.startswith("GPS looks static") for w in rep.warnings)
    syn, pairs = _rtk(**SHORT)
    syn.drive.gps = dataclasses.replace(
        g, lat_deg=np.full(len(g), g.lat_deg[0]), lon_deg=np.full(len(g), g.lon_deg[0])
    )
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    assert any(w.startswith("GPS looks static over frames") for w in rep.warnings), rep.warnings


def test_a_scale_error_within_the_height_tolerance_still_warns() -> None:
    """A 2.5 % scale error (a focal length or camera height that far off) is inside the 5 %
    height tolerance but many σ off: it warns, naming height_m and the focal length."""
    syn, pairs = _rtk(scale=1.025)
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    msg = [w for w in rep.warnings if "focal length (fx, fy)" in w]
    assert len(msg) == 1, rep.warnings
    # height_m 1.025 for a 1.000 m camera: too large; or a focal length too short
    assert "height_m may be 2.6% too large" in msg[0], msg[0]
    assert "focal length (fx, fy) 2.5% too short" in msg[0], msg[0]
    assert not any(w.startswith("camera.yaml height_m") for w in rep.warnings)


def test_a_log_that_agrees_as_given_is_not_called_a_file_mistake() -> None:
    """GPS 5 cm noisy logged with a 0.001 HDOP: fixes are rejected, which sends the check to the
    GPS-file hypotheses. This straight drive mirrored east-west agrees with vision as well as the
    log itself: no "longitude flipped" (it was named before the log as given was tried)."""
    syn, pairs = _rtk(hdop=0.001, gps_sigma_m=0.05)
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    assert any("rejected as outliers" in w for w in rep.warnings), rep.warnings
    assert not any("Fix the GPS file" in w for w in rep.warnings), rep.warnings
    assert "gps_hypothesis" not in rep.checks


def test_a_scale_that_changes_along_the_drive_is_named() -> None:
    """Vision's scale swinging ±12 % along the drive (a lens distortion left out of camera.yaml
    does this as the road moves through the image) scatters the GPS windows' length ratios
    several times their own σ: a warning names camera.yaml's dist and a GPS clock offset. The
    clean drive's ratios scatter about 1x and stay quiet."""
    syn, pairs = _rtk()
    swung = []
    for k, p in enumerate(pairs):
        s = 1.0 + 0.12 * np.sin(2 * np.pi * k / 20)
        q = copy.copy(p)
        q.t_b_from_a_m, q.points_cam_a_m = p.t_b_from_a_m * s, p.points_cam_a_m * s
        swung.append(q)
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, swung)
    assert rep.checks["ratio_scatter"] > 5
    msg = [w for w in rep.warnings if w.startswith("GPS/visual length ratios scatter")]
    assert len(msg) == 1 and "lens distortion (dist)" in msg[0] and "GPS clock" in msg[0]
    _, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, pairs)
    assert rep.checks["ratio_scatter"] < 2
    assert not any("scatter" in w for w in rep.warnings)
