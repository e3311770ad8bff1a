"""The stage fingerprints stored in poses_report.json and map_report.json must stay valid across
refactors (a resumed old run must still resume): fixed inputs give fixed values.

The expected values were recomputed when issue 31 added the GPS altitude, OBD speeds and the
plausibility checks' version to the poses key and the pairs' content, camera and vertical datum to
the map key, and issue 28 the mount (MappingConfig.estimate_mount, camera.yaml mount) to
the poses key; issues 29 and 30 added MappingConfig.surface_source, dense and bundle_* (both keys);
bundle_relief_sigma_m's default went from 3 mm to 1 cm and bundle_placement_length_m and bundle_loop_* came (issue 30);
bundle_adjust became the default, bundle_refine_focal and bundle_focal_sigma came and the poses key
holds the bundle's version (issue 30); the map key also moved with DenseHeightConfig.hole_fill_m
(issue 29); bundle_refine_k1 and bundle_k1_sigma came (issue 30); dense_single_view came
(issue 28); DenseHeightConfig.fallback_levels and step_max_sigma came (the map key);
grade_window_m (both keys) and dense_single_view_relief_m came (issue 28), then grade_sigma_pct
(both keys), dense_visible_k and the dense surface's code version (the map key), the
grade's version (the poses key); DenseHeightConfig.slant_sigmas and the dense surface's code
version 4 (the map key); BUNDLE_VERSION 6 (the poses key, issue 30: track links compared beyond
the pairs' smooth disagreement); BUNDLE_VERSION 7 (the poses key: that removal bounded by the
pairs' stated uncertainty); BUNDLE_VERSION 8 (the poses key, issue 29: the bundle's points'
steps on dense blocks and one BLAS thread, poses changed at rounding level); BUNDLE_VERSION 9
(the reduced Jacobian's point products as sparse matrices; rounding level); POSES_VERSION 2 (the
poses key: the ENU origin at the middle frame, no_motion pairs held together); DENSE_SURFACE_VERSION
10 (the map key: cloud.ply heights ellipsoidal); POSES_VERSION 3 (the poses key: the mount's
direction of travel turned back by half of each pair's turn); gps_sigma_from_log, gps_sigma_rtk_fixed_m and
gps_sigma_rtk_float_m (both keys; a log's stated σ / fix quality enter the poses key only when
gps_sigma_from_log is on, camera.yaml's gps_antenna_m only when given); CHECKS_VERSION 4 (the poses key: the scale note at 2.5 σ); DenseHeightConfig.max_depth_limit_m (the map key).
DENSE_SURFACE_VERSION 11 (the map key: a hole across a pothole wall ramps); cross_fall_pct (both keys);
POSES_VERSION 4 (the poses key: fixes off the visual consensus held out).
A change of MappingConfig's fields changes them legitimately. The keys must also
change with what the outputs depend on (below)."""

from __future__ import annotations

import numpy as np

from roadsurf.mapping import globalmap, poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.types import Trajectory
from tests.mapping.synth import make_synthetic


def test_poses_fingerprint_is_unchanged() -> None:
    syn = make_synthetic(n=6, seed=3, failed=(2,))
    assert poses._fingerprint(MappingConfig(), syn.drive, syn.pairs) == "43f6ce5d3fb26a1e"
    syn = make_synthetic(n=6, seed=3, with_gps=False)
    assert poses._fingerprint(MappingConfig(), syn.drive, syn.pairs) == "87faf849237ed5bb"


def test_globalmap_fingerprint_is_unchanged() -> None:
    syn = make_synthetic(n=6, seed=3, failed=(2,))
    traj = Trajectory(
        filenames=[f.filename for f in syn.drive.frames],
        frame_indices=np.arange(6),
        timestamp_s=np.arange(6) * 0.05,
        world_from_cam=syn.world_from_cam,
        source=["fused"] * 6,
        reference=None,
        segment=np.zeros(6, int),
    )
    assert globalmap._fingerprint(MappingConfig(), syn.pairs, traj) == "108d7a3c6660cfa9"


def test_poses_key_follows_the_gps_altitude() -> None:
    syn = make_synthetic(n=6, seed=3, gps_hz=20.0)
    assert len(syn.drive.gps) > 0
    key = poses._fingerprint(MappingConfig(), syn.drive, syn.pairs)
    syn.drive.gps.alt_m = syn.drive.gps.alt_m + 5.0
    assert poses._fingerprint(MappingConfig(), syn.drive, syn.pairs) != key


def test_poses_key_follows_the_stated_accuracy_and_the_antenna() -> None:
    import dataclasses

    syn = make_synthetic(n=6, seed=3, gps_hz=20.0)
    cfg = MappingConfig(gps_sigma_from_log=True)
    key = poses._fingerprint(cfg, syn.drive, syn.pairs)
    key_default = poses._fingerprint(MappingConfig(), syn.drive, syn.pairs)
    g = syn.drive.gps
    g.quality = np.full(len(g), 4)
    k_rtk = poses._fingerprint(cfg, syn.drive, syn.pairs)
    g.sigma_m = np.full(len(g), 0.02)
    k_sig = poses._fingerprint(cfg, syn.drive, syn.pairs)
    assert len({key, k_rtk, k_sig}) == 3
    # unused by default: the default key stays
    assert poses._fingerprint(MappingConfig(), syn.drive, syn.pairs) == key_default
    syn.drive.camera = dataclasses.replace(syn.drive.camera, gps_antenna_m=(-1.5, 0.0, 0.9))
    assert poses._fingerprint(MappingConfig(), syn.drive, syn.pairs) != key_default


def test_map_key_follows_the_pairs_content(tmp_path) -> None:
    """A recomputed pair with the same number of points (other content) rebuilds the map."""
    import copy

    from roadsurf.io.runfolder import RunFolder, fingerprint_path

    syn = make_synthetic(n=6, seed=3)
    traj = Trajectory(
        filenames=[f.filename for f in syn.drive.frames],
        frame_indices=np.arange(6),
        timestamp_s=np.arange(6) * 0.05,
        world_from_cam=syn.world_from_cam,
        source=["fused"] * 6,
        reference=None,
    )
    cfg = MappingConfig()
    key = globalmap._fingerprint(cfg, syn.pairs, traj, syn.drive, tmp_path)
    moved = copy.copy(syn.pairs[2])
    moved.points_cam_a_m = moved.points_cam_a_m + [0.0, 0.0, 0.001]
    changed = [*syn.pairs[:2], moved, *syn.pairs[3:]]
    assert moved.n_points == syn.pairs[2].n_points
    assert globalmap._fingerprint(cfg, changed, traj, syn.drive, tmp_path) != key
    # the reconstruction's fingerprint of a pair (its settings, camera, image files) counts too
    run = RunFolder(tmp_path)
    run.pairs_dir.mkdir()
    fingerprint_path(run.pair(0, 1)).write_text("0123456789abcdef\n")
    assert globalmap._fingerprint(cfg, syn.pairs, traj, syn.drive, tmp_path) != key
