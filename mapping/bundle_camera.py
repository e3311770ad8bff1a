"""The camera and the pairs the later stages use once the bundle refined the intrinsics (issue
30, ``bundle_refine_focal`` / ``bundle_refine_k1``; both off by default, and then nothing here
changes anything).

A pair's geometry rests on the camera it was solved with: its rays are camera.yaml's K⁻¹ of its
undistorted pixels, its motion (R, t), road plane and points were fitted to those rays. Handing
the later stages a camera with another focal length while they keep the pair's own R, t, plane
and points mixes two cameras: the dense matching (``reconstruction.dense``) builds its plane +
parallax model from the pair's R, t and plane with the new K, the map places the pair's points
(triangulated with the old K) beside a mosaic projected with the new one. A 1.5 % focal error
puts a point 1 m off the image centre 15 mm sideways.

So with a refined camera every ok pair is re-derived with it (``refined_pairs``):

- its own motion, mapped to the refined focal (``pair_motion_with_focal``: the camera.yaml
  solution is the true scene mapped by A = diag(e^ψ, e^ψ, 1) in camera a, then scaled by the
  camera height), so that the refined K with it keeps the pair's own epipolar fit. Not the
  refined poses' motion: that moved the dense matching off its images' geometry (simulated
  rolling-shutter drive at 30 fps, 20 ms readout, correct focal: flat MAE 1.42 -> 2.05 mm,
  seam step 0.37 -> 1.79 mm, defect depth MAE 4.4 -> 10.4 mm);
- its matches' pixels are the refined camera's ideal pixels (the bundle's k1 model,
  ``bundle_problem.true_px_from_observed_px``; unchanged without a k1 correction: an ideal pixel
  stays where it is, only its ray changes with the focal);
- its points are re-triangulated from those rays with that motion (a rolling shutter's rows each
  from their own pose, ``reconstruction.rolling_shutter.poses_at``, as the pair was solved);
  a match that no longer triangulates in front of both cameras is dropped;
- its road plane is refitted to them (``core.fits.fit_plane_z_trimmed`` with the
  reconstruction's ``plane_trim_k``), the points' plane distances and F follow.

Not re-derived: the homography H (pixels to pixels: it does not depend on K; the dense matching
only logs it against its own), the points' covariances (kept on disk only, read by the viewer and
the studies), the rejected matches (the viewer's). The distortion's higher terms (k2, k3 and
the tangential ones) stay camera.yaml's, and the refined focal changes the radius they are
applied at by the focal scale (second order: a 1.5 % focal error scales k2 r⁴ by 6 %).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.atomic import read_json
from roadsurf.core.camera import Camera, normalised_from_px
from roadsurf.core.fits import fit_plane_z_trimmed, plane_signed_distance
from roadsurf.io import runfolder as rf
from roadsurf.io.drive import Drive
from roadsurf.mapping.bundle_terms import pair_translation, true_px_from_observed_px
from roadsurf.mapping.pairscale import rescaled_pairs
from roadsurf.mapping.types import Trajectory

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


def refined_camera(camera: Camera, bundle_report: dict[str, Any]) -> Camera:
    """The camera the later stages use: camera.yaml's with the bundle's refined focal length
    (fx, fy times the report's "focal_scale", the principal point kept) and k1 (``dist[0]``,
    the report's "k1"), each where the bundle estimated it (a report without either: the camera
    unchanged, the same object)."""
    if "k1" not in bundle_report and "focal_scale" not in bundle_report:
        return camera
    s = float(bundle_report.get("focal_scale", 1.0))
    dist = (float(bundle_report.get("k1", camera.dist[0])), *camera.dist[1:])
    return dataclasses.replace(camera, fx=camera.fx * s, fy=camera.fy * s, dist=dist)


def refined_inputs(
    drive: Drive, pairs: list[PairResult], traj: Trajectory, run_dir: Path, plane_trim_k: float
) -> tuple[Drive, list[PairResult]]:
    """The drive with the refined camera and the pairs re-derived with it (module docstring),
    from the bundle's figures in ``run_dir``'s poses report; the inputs unchanged when the
    report holds no refined intrinsics (the refinement off, or no bundle)."""
    path = run_dir / rf.POSES_REPORT
    rep = read_json(path).get("bundle", {}) if path.is_file() else {}
    cam = refined_camera(drive.camera, rep or {})
    if cam is drive.camera:
        return drive, pairs
    new = refined_pairs(pairs, drive.camera, cam, traj, plane_trim_k)
    log.info(
        "bundle: the later stages use fx %.2f -> %.2f px, k1 %.4f -> %.4f; %d pairs re-derived",
        drive.camera.fx, cam.fx, drive.camera.dist[0], cam.dist[0],
        sum(a is not b for a, b in zip(pairs, new, strict=True)),
    )  # fmt: skip
    return dataclasses.replace(drive, camera=cam), new


def later_stage_inputs(
    drive: Drive, pairs: list[PairResult], traj: Trajectory, run_dir: Path, plane_trim_k: float
) -> tuple[Drive, list[PairResult]]:
    """The drive and pairs the stages after the poses (map, dense surface, detection) use: the
    camera on the mount the poses used (given or estimated: ``traj.mount_deg``) and with the
    bundle's refined intrinsics where it estimated them, the pairs re-derived with them
    (``refined_inputs``). ``pipeline.run`` and the benchmarks that re-run a stage on a finished
    run folder call this one function. Pairs whose scale disagrees with the trajectory's are
    rescaled to it (``mapping.pairscale``; its warning joins ``drive.warnings``, the report's)."""
    if traj.mount_deg is not None and traj.mount_deg != drive.camera.mount_deg:
        camera = dataclasses.replace(drive.camera, mount_deg=traj.mount_deg)
        drive = dataclasses.replace(drive, camera=camera)
    drive, pairs = refined_inputs(drive, pairs, traj, run_dir, plane_trim_k)
    return drive, rescaled_pairs(pairs, traj, drive.warnings)


def refined_pairs(
    pairs: list[PairResult],
    calibrated: Camera,
    refined: Camera,
    traj: Trajectory,
    plane_trim_k: float,
) -> list[PairResult]:
    """Each ok pair whose frames are both posed, re-derived with the ``refined`` camera (module
    docstring); ``calibrated`` is the camera the pairs were solved with (camera.yaml's), the
    trajectory gives the frames' times. Other pairs are returned as they are (the same
    objects)."""
    pose_of = {fn: i for i, fn in enumerate(traj.filenames)}
    K = refined.K
    psi = float(np.log(refined.fx / calibrated.fx))  # the focal's log scale ψ
    # the k1 correction in the bundle's model (observed = true (1 + κ r²))
    kappa = float(refined.dist[0] - calibrated.dist[0])
    out: list[PairResult] = []
    for p in pairs:
        ia, ib = pose_of.get(p.frame_a), pose_of.get(p.frame_b)
        if not p.ok or p.n_points == 0 or ia is None or ib is None:
            out.append(p)
            continue
        R, t = pair_motion_with_focal(p.R_b_from_a, p.t_b_from_a_m, p.plane, psi)
        pa = true_px_from_observed_px(np.asarray(p.px_a, float), K, kappa)
        pb = true_px_from_observed_px(np.asarray(p.px_b, float), K, kappa)
        sa = sb = None
        if calibrated.readout_s > 0 and "rs_iterations" in p.config_name:
            # each row from its own pose, as the pair was solved (reconstruction.rolling_shutter)
            from roadsurf.reconstruction.rolling_shutter import row_times_s

            dt = float(traj.timestamp_s[ib] - traj.timestamp_s[ia])
            rows = (calibrated.distort_px(np.asarray(px, float))[:, 1] for px in (p.px_a, p.px_b))
            ta, tb = (row_times_s(v, calibrated.height, calibrated.readout_s) for v in rows)
            sa, sb = ta / dt, 1.0 + tb / dt
        X = _triangulate(pa, pb, K, R, t, sa, sb)
        Xb = X @ R.T + t
        keep = np.all(np.isfinite(X), axis=1) & (X[:, 2] > 0) & (Xb[:, 2] > 0)
        if keep.sum() < 3:
            log.warning("bundle: pair %s -> %s kept as solved (no refined points)", p.frame_a,
                        p.frame_b)  # fmt: skip
            out.append(p)
            continue
        q = copy.copy(p)  # a StoredPairResult keeps its on-disk fields on disk
        if not keep.all():
            q.match_idx = np.asarray(p.match_idx)[keep]
        X, pa, pb = X[keep], pa[keep], pb[keep]
        plane, _ = fit_plane_z_trimmed(X, plane_trim_k)
        q.points_cam_a_m, q.px_a, q.px_b = X, pa, pb
        q.plane = plane
        q.plane_dist_m = plane_signed_distance(X, plane)
        q.R_b_from_a, q.t_b_from_a_m = R.copy(), t.copy()
        from roadsurf.reconstruction.geometry import fundamental_from_pose

        q.F = fundamental_from_pose(R, t, K)
        out.append(q)
    return out


def pair_motion_with_focal(
    R: np.ndarray, t: np.ndarray, plane: np.ndarray, psi: float
) -> tuple[np.ndarray, np.ndarray]:
    """A pair's motion X_b = R X_a + t (3, 3), (3,) m, solved with camera.yaml's focal and scaled
    by the camera height over its road plane (p0, p1, p2), under the focal scale e^ψ: the
    camera.yaml solution is the true scene mapped by A = diag(e^ψ, e^ψ, 1) and scaled by
    1 / |A n̂| (``bundle_problem.pair_translation``), so R = the rotation nearest A⁻¹ R A and t =
    A⁻¹ t |A n| (n the pair's unit road normal). The same epipolar geometry in pixels with the
    refined K, to first order in the inter-frame rotation."""
    if psi == 0.0:
        return np.asarray(R, float).copy(), np.asarray(t, float).copy()
    n = np.array([-plane[0], -plane[1], 1.0]) if np.all(np.isfinite(plane)) else np.eye(3)[2]
    n = n / np.linalg.norm(n)
    t2, _ = pair_translation(np.asarray(t, float)[None], n[None], psi)
    a = np.array([np.exp(psi), np.exp(psi), 1.0])
    U, _, Vt = np.linalg.svd(np.asarray(R, float) * a[None, :] / a[:, None])  # A⁻¹ R A
    R2 = U @ Vt
    if np.linalg.det(R2) < 0:
        R2 = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R2, t2[0]


def _triangulate(
    pa: np.ndarray,
    pb: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    s_a: np.ndarray | None,
    s_b: np.ndarray | None,
) -> np.ndarray:
    """(N, 3) points in camera a (m) from ideal pixels pa, pb (N, 2) with intrinsics K (3, 3)
    and X_b = R X_a + t (m); s_a, s_b (N,): a rolling shutter's rows as fractions of the motion
    a -> b (``rolling_shutter.poses_at``; None: a global shutter)."""
    from roadsurf.reconstruction.rolling_shutter import poses_at, triangulate_per_ray

    xa, xb = normalised_from_px(pa, K), normalised_from_px(pb, K)
    n = len(xa)
    if s_a is None or s_b is None:
        Ra, ta = np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3))
        Rb, tb = np.broadcast_to(R, (n, 3, 3)), np.broadcast_to(t, (n, 3))
    else:
        Ra, ta = poses_at(R, t, s_a)
        Rb, tb = poses_at(R, t, s_b)
    return triangulate_per_ray(xa, xb, Ra, ta, Rb, tb)
