"""Rolling shutter end to end: a rendered highway drive (25 m/s, 60 fps, 10 ms readout, small
frames) through the reconstruction stage, whose frame intervals come from frames.csv (with the
simulator's trigger jitter), against the true poses."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from roadsurf.io.drive import load_drive
from roadsurf.io.formats import read_csv
from roadsurf.reconstruction import stage
from roadsurf.reconstruction.config import FeatureConfig, ReconstructionConfig
from roadsurf.simulation.scenarios import simulate

SMALL = {"width": 320, "height": 240, "fx": 300.0}


@pytest.fixture(scope="module")
def rs_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rs") / "drive"
    return simulate("highway", out, n_frames=4, progress=False, readout_s=0.01, **SMALL)


def _true_baselines(drive_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    poses = {}
    for r in read_csv(drive_dir / "truth/poses.csv"):
        q = [float(r[k]) for k in ("qx", "qy", "qz", "qw")]
        C = np.array([float(r[k]) for k in ("easting_m", "northing_m", "up_m")])
        poses[r["filename"]] = (Rotation.from_quat(q).as_matrix(), C)
    return poses


def test_stage_corrects_a_rolling_shutter_drive(rs_drive: Path, tmp_path: Path) -> None:
    drive = load_drive(rs_drive)
    assert drive.camera.readout_s == 0.01
    truth = _true_baselines(rs_drive)
    cfg = ReconstructionConfig(features=FeatureConfig(max_features=1500))
    scale = {}
    for on in (True, False):
        pairs = stage.run(replace(cfg, rolling_shutter=on), drive, tmp_path / f"run{on}")
        assert all(p.ok for p in pairs), [p.reason for p in pairs]
        errs = []
        for p in pairs:
            (Ra, Ca), (Rb, Cb) = truth[p.frame_a], truth[p.frame_b]
            R, t = Rb.T @ Ra, Rb.T @ (Ca - Cb)
            errs.append(np.linalg.norm(p.t_b_from_a_m) / np.linalg.norm(t) - 1)
            if on:
                dR = Rotation.from_matrix(p.R_b_from_a.T @ R).magnitude()
                assert np.degrees(dR) < 0.2
                assert "rs_iterations=" in p.config_name
        scale[on] = np.array(errs)
    assert np.all(np.abs(scale[True]) < 0.015), scale[True]
    assert np.all(scale[False] > 0.25), scale[False]  # the baseline reads ~40% long


def test_pair_fingerprint_covers_the_timestamps_only_with_a_rolling_shutter(
    rs_drive: Path,
) -> None:
    drive = load_drive(rs_drive)
    cfg = ReconstructionConfig()
    a, b = drive.frames[:2]
    moved = replace(b, timestamp_s=b.timestamp_s + 0.001)
    rs, gs = drive.camera, replace(drive.camera, readout_s=0.0)
    assert stage.pair_fingerprint(cfg, rs, a, b) != stage.pair_fingerprint(cfg, rs, a, moved)
    assert stage.pair_fingerprint(cfg, gs, a, b) == stage.pair_fingerprint(cfg, gs, a, moved)
