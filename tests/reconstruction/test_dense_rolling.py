"""Rolling shutter in the dense matching (reconstruction.dense.rolling): each frame is read at
the row that saw the road point, and the dense heights of a rolling-shutter pair no longer
drift across the rows."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from roadsurf.core.camera import Camera
from roadsurf.io.drive import load_drive, read_gray
from roadsurf.reconstruction.api import reconstruct_pair
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.parallax import dense_height
from roadsurf.reconstruction.dense.rolling import raw_px_from_plane_px
from roadsurf.reconstruction.rolling_shutter import poses_at, row_times_s
from roadsurf.simulation.scenarios import simulate

CAM = Camera(320, 240, 300.0, 300.0, 159.5, 119.5, 1.1, 15.0)
R = np.eye(3)
T = np.array([0.0, 0.4, 0.0])  # X_b = X_a + t: b 0.4 m ahead (image up), nadir camera
PLANE = np.array([0.0, 0.0, 1.1])  # z = 1.1 m in camera a


def _grid() -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[10:230:20, 10:310:20].astype(float)
    return u, v


def test_a_global_shutter_reads_the_timestamps_poses() -> None:
    u, v = _grid()
    ua, va = raw_px_from_plane_px(u, v, CAM, R, T, PLANE, 1 / 15, 0)
    assert np.allclose(ua, u) and np.allclose(va, v)
    ub, vb = raw_px_from_plane_px(u, v, CAM, R, T, PLANE, 1 / 15, 1)
    assert np.allclose(ub, u) and np.allclose(vb, v + 0.4 * 300 / 1.1)  # H of a translation


@pytest.mark.parametrize("frame", [0, 1])
def test_each_pixel_is_read_at_the_row_that_saw_it(frame: int) -> None:
    cam = dataclasses.replace(CAM, readout_s=0.03)
    u, v = _grid()
    ur, vr = raw_px_from_plane_px(u, v, cam, R, T, PLANE, 1 / 15, frame)
    # the plane point behind (u, v), seen from the pose of row vr, projects to (ur, vr)
    d = np.stack([(u.ravel() - cam.cx) / cam.fx, (v.ravel() - cam.cy) / cam.fy, np.ones(u.size)], 1)
    X = d * 1.1
    s = frame + row_times_s(vr.ravel(), cam.height, cam.readout_s) * 15
    Rs, ts = poses_at(R, T, s)
    Xs = np.einsum("nij,nj->ni", Rs, X) + ts
    q = Xs @ cam.K.T
    assert np.allclose(q[:, 0] / q[:, 2], ur.ravel(), atol=0.02)
    assert np.allclose(q[:, 1] / q[:, 2], vr.ravel(), atol=0.02)
    # and the readout moved it: the road moves down the image while the rows are read
    assert (vr - raw_px_from_plane_px(u, v, CAM, R, T, PLANE, 1 / 15, frame)[1]).max() > 5


def test_horizon_pixels_are_nan() -> None:
    tilted = np.array([0.0, -8.0, 1.1])  # a plane so steep that the top rows never meet it
    u, v = _grid()
    ua, _ = raw_px_from_plane_px(u, v, CAM, R, T, tilted, 1 / 15, 0)
    assert np.isnan(ua).any() and np.isfinite(ua).any()
    # a frame b turned to look up sees the road behind it: NaN, never a sign-flipped pixel
    up = np.diag([1.0, -1.0, -1.0])
    ub, _ = raw_px_from_plane_px(u, v, CAM, up, T, PLANE, 1 / 15, 1)
    assert np.isnan(ub).all()


def _flat_pair(out: Path, readout_s: float) -> Path:
    # 6 m/s at 15 fps; a 30 ms readout moves the camera 18 cm while it reads one frame
    return simulate(
        "flat", out, n_frames=2, progress=False, readout_s=readout_s,
        width=320, height=240, fx=300.0, unevenness_m=0.0, undulation_m=0.0,
    )  # fmt: skip


def _spread_mm(drive_dir: Path, use_rows: bool) -> tuple[float, float]:
    """Robust spread (mm) of a flat road's dense heights, and the share of valid pixels."""
    drive = load_drive(drive_dir)
    a, b = drive.frames
    res = reconstruct_pair(a, b, drive.camera, ReconstructionConfig())
    assert res.ok, res.reason
    dt = (b.timestamp_s - a.timestamp_s) if use_rows else None
    dh = dense_height(
        read_gray(a), read_gray(b), drive.camera, res.R_b_from_a, res.t_b_from_a_m, res.plane,
        cfg=DenseHeightConfig(device="cpu"), frame_dt_s=dt,
    )  # fmt: skip
    h = dh.height_m[dh.valid]
    return float(1.4826 * np.median(np.abs(h - np.median(h))) * 1e3), float(dh.valid.mean())


def test_the_heights_of_a_rolling_shutter_pair_stay_level(tmp_path: Path) -> None:
    rs = _flat_pair(tmp_path / "rs", 0.03)
    gs = _flat_pair(tmp_path / "gs", 0.0)
    plain, _ = _spread_mm(rs, use_rows=False)
    rolled, valid = _spread_mm(rs, use_rows=True)
    twin, _ = _spread_mm(gs, use_rows=True)
    # measured: 48 mm without the rows' poses, 1.5 mm with them, the twin 1.6 mm
    assert valid > 0.3
    assert rolled < 0.2 * plain  # the rows' poses take out the drift
    assert rolled < 1.5 * twin + 0.3  # ... down to about the global-shutter twin's noise
