"""A forward-tilted camera at highway speed with a rolling shutter stretches the road in the
later image beyond what SIFT's descriptors match; the stretch retry detects image b again on
vertically compressed views (``features.detect_stretched``) and the pair reconstructs."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from roadsurf.io.drive import load_drive, read_gray
from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.api import reconstruct_features, retry_stretched
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.simulation.scenarios import simulate


@pytest.fixture(scope="module")
def fast_tilted_rs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # 100 km/h, 50 fps, 20 ms readout: the camera moves 0.56 m while one frame is read
    out = tmp_path_factory.mktemp("rs") / "drive"
    return simulate(
        "highway",
        out,
        n_frames=2,
        progress=False,
        readout_s=0.02,
        fps=50.0,
        mount_pitch_deg=40.0,
        speed_mps=27.78,
    )


def test_detect_stretched_keeps_recorded_pixel_positions() -> None:
    rng = np.random.default_rng(0)
    img = (rng.random((240, 320)) * 255).astype(np.uint8)
    img = np.kron(img[::4, ::4], np.ones((4, 4), np.uint8))  # blobs SIFT finds at any scale
    cfg = ReconstructionConfig().features
    f = feat.detect_stretched(img, cfg, 0.5)
    assert len(f.keypoints_px) > 50
    assert f.keypoints_px[:, 1].max() > 200  # mapped back to the full height, not 0..120
    assert f.keypoints_px[:, 1].min() >= -0.5
    with pytest.raises(ValueError, match="outside"):
        feat.detect_stretched(img, cfg, 1.5)


def test_the_stretch_retry_reconstructs_a_pair_plain_matching_loses(fast_tilted_rs: Path) -> None:
    drive = load_drive(fast_tilted_rs)
    cfg = ReconstructionConfig()
    a, b = drive.frames[0], drive.frames[1]
    ga, gb = read_gray(a), read_gray(b)
    fa, fb = feat.detect(ga, cfg.features), feat.detect(gb, cfg.features)
    dt = b.timestamp_s - a.timestamp_s
    plain = reconstruct_features(fa, fb, drive.camera, cfg, frame_dt_s=dt)
    assert not plain.ok, "the plain match was expected to fail on this drive"
    off = retry_stretched(
        plain, fa, gb, drive.camera, replace(cfg, features=replace(cfg.features, stretch_retry=()))
    )
    assert off is plain and not off.ok
    res = retry_stretched(plain, fa, gb, drive.camera, cfg, frame_dt_s=dt)
    assert res.ok, res.reason
    assert res.stretch_b < 1
    # metric baseline against the true camera centres (truth/poses.csv, ENU metres)
    truth = np.genfromtxt(fast_tilted_rs / "truth" / "poses.csv", delimiter=",", names=True)
    enu = np.stack([truth["easting_m"], truth["northing_m"], truth["up_m"]], axis=1)
    true_travel = float(np.linalg.norm(enu[1] - enu[0]))
    assert float(np.linalg.norm(res.t_b_from_a_m)) == pytest.approx(true_travel, rel=0.02)
