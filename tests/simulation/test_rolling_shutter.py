"""Rolling shutter in the simulator (issue 28): each row from its own pose, camera.yaml's
readout_s, the timestamp convention and the refusal of a readout longer than a frame."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from roadsurf.core.errors import ConfigError
from roadsurf.io.drive import load_drive
from roadsurf.io.formats import read_csv
from roadsurf.simulation.build import build_world
from roadsurf.simulation.render import Renderer
from roadsurf.simulation.scenarios import make_config, simulate

SMALL = {"width": 160, "height": 120, "fx": 150.0}
QUIET = {"n_potholes": 0, "n_cracks": 0, "n_ruts": 0, "n_lane_markings": 0}
QUIET |= {"n_shadows": 0, "n_oil_stains": 0}


@pytest.mark.parametrize("pitch", [0.0, 30.0])
def test_each_row_is_rendered_from_its_own_pose(pitch: float) -> None:
    """Row v of a rolling-shutter frame stamped t is row v of the global-shutter frame
    rendered from the pose at t + readout_s · v / height (one ray per pixel, so a row has
    one time); the global-shutter frame at t differs by far more."""
    kw = dict(SMALL, supersample=1, mount_pitch_deg=pitch)
    rs = build_world(make_config("highway", readout_s=0.01, **kw), 5, 4)
    gs = build_world(make_config("highway", readout_s=0.0, **kw), 5, 4)
    t = float(rs.frame_times[1])
    frame = Renderer(rs).render(rs.pose(t)).radiance
    r_gs = Renderer(gs)
    for v in (0, 40, 80, 119):
        row = r_gs.render(gs.pose(t + 0.01 * v / 120)).radiance[v]
        assert np.abs(row - frame[v]).max() < 1e-3, v
    still = r_gs.render(gs.pose(t)).radiance
    assert np.abs(still[100] - frame[100]).max() > 0.05  # 8 mm of travel at row 100


def test_readout_goes_to_camera_yaml_and_poses_are_the_first_rows(tmp_path: Path) -> None:
    out = simulate("highway", tmp_path / "rs", n_frames=3, progress=False, readout_s=0.012,
                   **SMALL, **QUIET)  # fmt: skip
    assert "readout_s: 0.012\n" in (out / "camera.yaml").read_text()
    drive = load_drive(out)
    assert drive.camera.readout_s == 0.012
    # truth/poses.csv: the pose at the frame's timestamp, the first row's
    world = build_world(make_config("highway", readout_s=0.012, **SMALL, **QUIET), 505, 3)
    for frame, row in zip(drive.frames, read_csv(out / "truth/poses.csv"), strict=True):
        pose = world.pose(frame.timestamp_s)
        assert float(row["timestamp_s"]) == pytest.approx(frame.timestamp_s, abs=1e-6)
        C = [float(row[k]) for k in ("easting_m", "northing_m", "up_m")]
        np.testing.assert_allclose(C[:2] - np.array([world.origin_e_m, world.origin_n_m]),
                                   pose.C[:2], atol=2e-3)  # fmt: skip
        q = [float(row[k]) for k in ("qx", "qy", "qz", "qw")]
        dR = Rotation.from_quat(q).as_matrix().T @ pose.R
        assert math.degrees(Rotation.from_matrix(dR).magnitude()) < 0.01
    gs = simulate("highway", tmp_path / "gs", n_frames=2, progress=False, **SMALL, **QUIET)
    assert "readout" not in (gs / "camera.yaml").read_text()
    assert load_drive(gs).camera.readout_s == 0.0


def test_a_readout_longer_than_a_frame_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"readout_s = 0.02 s is longer than one frame period"):
        make_config("highway", readout_s=0.02)  # 60 fps: 16.7 ms per frame
    with pytest.raises(ConfigError, match=r"fps to <= 50 Hz"):
        make_config("highway", readout_s=0.02)
    make_config("highway", readout_s=0.02, fps=50.0)
    with pytest.raises(ConfigError, match="readout_s"):
        make_config("flat", readout_s=0.25)
    with pytest.raises(ConfigError, match="readout_s"):
        make_config("flat", readout_s=-0.001)
