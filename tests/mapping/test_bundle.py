"""Bundle adjustment after the pose graph (mapping.bundle, issue 30) on seeded synthetic drives
whose frames share road points: it must beat the pose graph against the truth, reject a bad
GPS fix, and recover a GPS latency."""

from __future__ import annotations

import dataclasses

import numpy as np

from roadsurf.core.geometry import enu_from_lla, lla_from_enu
from roadsurf.mapping import poses
from roadsurf.mapping.bundle import refine_poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.pose_gps import gps_enu
from roadsurf.mapping.types import PoseReport
from tests.mapping.bundle_synth import make_track_drive
from tests.mapping.synth import REF

CFG = MappingConfig(gps_sigma_m=0.02)


def _errors(traj, syn) -> tuple[float, float]:
    """Camera-centre RMSE (m) and rotation RMSE (deg) against the truth."""
    lla = lla_from_enu(traj.positions_enu_m, traj.reference)
    p = enu_from_lla(lla[:, 0], lla[:, 1], lla[:, 2], REF)
    e = p - syn.world_from_cam[:, :3, 3]
    R, Rt = traj.world_from_cam[:, :3, :3], syn.world_from_cam[:, :3, :3]
    c = np.clip((np.einsum("nij,nij->n", R, Rt) - 1) / 2, -1, 1)
    return float(np.sqrt(np.mean(np.sum(e**2, 1)))), float(
        np.sqrt(np.mean(np.degrees(np.arccos(c)) ** 2))
    )


def _relative_errors(W: np.ndarray, Wt: np.ndarray, k: int = 5) -> tuple[float, float]:
    """RMS error of the motion over k frames (m, deg): the shape, whatever the GPS placement."""
    et, er = [], []
    for i in range(len(W) - k):
        A = np.linalg.inv(W[i]) @ W[i + k]
        B = np.linalg.inv(Wt[i]) @ Wt[i + k]
        D = np.linalg.inv(B) @ A
        et.append(np.linalg.norm(D[:3, 3]))
        er.append(np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))))
    return float(np.sqrt(np.mean(np.square(et)))), float(np.sqrt(np.mean(np.square(er))))


def _both(syn, cfg: MappingConfig):
    off = poses.estimate_trajectory(cfg, syn.drive, syn.pairs)
    on = poses.estimate_trajectory(
        dataclasses.replace(cfg, bundle_adjust=True), syn.drive, syn.pairs
    )
    return off, on


def test_bundle_adjustment_reduces_the_pose_error() -> None:
    # consumer-grade GPS: the shape rests on the pairs (rotations 0.1°, scale 0.5 % off)
    syn = make_track_drive(n=40, seed=2, gps_hz=1.0, gps_sigma_m=0.3, rot_noise_deg=0.1)
    cfg = MappingConfig(gps_sigma_m=0.3)
    (t0, _), (t1, rep) = _both(syn, cfg)
    p0, r0 = _relative_errors(t0.world_from_cam, syn.world_from_cam)
    p1, r1 = _relative_errors(t1.world_from_cam, syn.world_from_cam)
    assert rep.bundle["n_tracks_3plus"] > 500
    assert rep.bundle["reprojection_rms_px_final"] < rep.bundle["reprojection_rms_px_initial"]
    assert r1 < 0.7 * r0, (r0, r1)
    assert p1 < 0.7 * p0, (p0, p1)


def test_a_gps_outlier_is_rejected() -> None:
    syn = make_track_drive(n=40, seed=3, gps_outliers={12: (0.6, -0.4)})
    traj, _ = poses.estimate_trajectory(CFG, syn.drive, syn.pairs)
    _, gps = gps_enu(CFG, syn.drive, traj.timestamp_s, PoseReport())
    pos_of = {i: i for i in range(len(traj.timestamp_s))}
    # every fix offered (the pose graph's own rejection bypassed): the bundle must find it
    W, rep = refine_poses(
        CFG, syn.drive, traj.timestamp_s, traj.world_from_cam, syn.pairs, pos_of, gps, None,
        traj.vehicle_from_cam,
    )  # fmt: skip
    assert [r["gps_index"] for r in rep["gps_rejected"]] == [12]
    traj.world_from_cam = W
    assert _errors(traj, syn)[0] < 0.02


def test_the_gps_time_offset_is_recovered() -> None:
    syn = make_track_drive(n=60, seed=1, gps_latency_s=0.06)
    (t0, _), (t1, rep) = _both(syn, CFG)
    assert abs(rep.bundle["time_offset_s"] - 0.06) < 0.010, rep.bundle["time_offset_s"]
    p0, _ = _errors(t0, syn)
    p1, _ = _errors(t1, syn)
    assert p0 > 0.1  # the pose graph, blind to the latency, is off by decimetres
    assert p1 < 0.03
