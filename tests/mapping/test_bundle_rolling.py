"""A rolling shutter inside the bundle adjustment (mapping.bundle, issue 30): with camera.yaml's
``readout_s`` each track observation is projected from the pose of its row's time (the frame's
motion over the readout from its neighbours, ``core.rolling.frame_motion``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from roadsurf.core.rolling import row_offset
from roadsurf.mapping import poses
from roadsurf.mapping.config import MappingConfig
from tests.mapping.bundle_synth import make_track_drive
from tests.mapping.test_bundle import _relative_errors


def _rolling_drive():
    """A seeded 30-frame drive with a 30 ms readout at 4 m/s and 1 Hz consumer GPS, and the
    mapping config its tests run with."""
    syn = make_track_drive(
        n=30, seed=2, width_px=640, density_per_m2=60, readout_s=0.03, gps_hz=1.0,
        gps_sigma_m=0.3,
    )  # fmt: skip
    return syn, MappingConfig(gps_sigma_m=0.3, bundle_max_time_offset_s=0.0)


def test_the_row_time_model_lowers_the_pose_error_of_a_rolling_shutter_drive() -> None:
    # 30 ms readout at 4 m/s: the camera moves 12 cm between the first and the last row (the
    # frames are 20 cm apart). Projected as if every row were taken at the frame's time the
    # tracks bend the poses: 5-frame error 39 mm / 0.51° against the pose graph's 8.8 mm /
    # 0.25° (measured, seed 2); with the rows' poses 4.6 mm / 0.16°
    syn, cfg = _rolling_drive()
    glob = dataclasses.replace(syn.drive.camera, readout_s=0.0)
    errs = {}
    for name, cam, ba in (
        ("pose graph", syn.drive.camera, False),
        ("global", glob, True),
        ("rows", syn.drive.camera, True),
    ):
        drive = dataclasses.replace(syn.drive, camera=cam)
        tr, _ = poses.estimate_trajectory(
            dataclasses.replace(cfg, bundle_adjust=ba), drive, syn.pairs
        )
        errs[name] = _relative_errors(tr.world_from_cam, syn.world_from_cam)
    (pg_t, pg_r), (g_t, g_r), (r_t, r_r) = errs["pose graph"], errs["global"], errs["rows"]
    assert r_t < 0.5 * g_t and r_r < 0.5 * g_r, errs
    assert r_t < pg_t and r_r < pg_r, errs


def test_a_row_offset_of_zero_time_is_the_frame_pose() -> None:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(5, 3))
    w, a = row_offset(v, np.zeros(5), rng.normal(size=(5, 3)), rng.normal(size=(5, 3)))
    assert np.array_equal(w, v) and not a.any()
    # a pure translation during the readout: the point is seen from the moved centre
    vel = np.tile([1.0, 0.0, 0.0], (5, 1))
    w, _ = row_offset(v, np.full(5, 0.01), vel, np.zeros((5, 3)))
    assert np.allclose(w, v - [0.01, 0.0, 0.0])


def test_a_rolling_shutter_bundle_keeps_the_pose_graphs_mean_tilt() -> None:
    # a roll of every camera about a straight track (the points turning with them) is a gauge:
    # GPS and the images do not see it, and the row-time terms tipped it 0.8-1.0° on a
    # simulated 30 fps drive (the map 18-19 mm beside its cameras). The window's mean tilt
    # stays the pose graph's (bundle_problem.TILT_MEAN_SIGMA_DEG); without that term this
    # drive's mean tilt moves 0.06° from it (seed 2, measured)
    from scipy.spatial.transform import Rotation

    syn, cfg = _rolling_drive()
    tilt = {}
    for ba in (False, True):
        tr, _ = poses.estimate_trajectory(
            dataclasses.replace(cfg, bundle_adjust=ba), syn.drive, syn.pairs
        )
        rel = np.einsum("nji,njk->nik", syn.world_from_cam[:, :3, :3], tr.world_from_cam[:, :3, :3])
        tilt[ba] = np.degrees(Rotation.from_matrix(rel).as_rotvec().mean(0)[:2])
    assert np.abs(tilt[True] - tilt[False]).max() < 0.02, tilt
