"""Pose of every frame: GPS + feature-chained stitching fused in one robust pose graph.

Dissertation Chapter 6 places frames between GPS fixes by chaining the pairwise transforms and
takes the heading from successive fixes (eq. 6.1, θ_k = arctan(−(x_k − x_{k−1})/(y_k − y_{k−1}))).
Here both sources go into one sparse robust least-squares problem over all frame poses
(world_from_cam in the local ENU frame):

- relative constraints from every ok pair's metric transform (cam_b_from_cam_a);
- absolute GPS constraints, each fix used as a measurement at its own timestamp: the predicted
  camera centre at the fix time is interpolated between the two frames around it, so no frame
  pose is ever interpolated from GPS;
- eq. 6.1 headings between successive fixes (weighted by the fix baseline);
- OBD speed (optional), a weak road-normal (tilt) prior, and a weak constant-velocity guess
  across failed pairs so the problem stays well posed;
- a robust loss, then a robust re-weighting (MAD of normalised residuals) and rejection of
  GPS fixes that disagree with the fused solution by more than ``gps_outlier_sigmas``.

Works through GPS gaps (vision carries), failed pairs (GPS bridges; if neither, a new segment
with a warning), and with no GPS at all (local frame, reference None, warning).

This module is the stage (``run``, ``estimate_trajectory``); the GPS preprocessing is in
``mapping.pose_gps``, the initial guess and segments in ``mapping.pose_init``, the solver in
``mapping.pose_graph``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.atomic import UNREADABLE, read_json_object, write_json_atomic
from roadsurf.core.config import to_dict
from roadsurf.core.fingerprint import Fingerprint
from roadsurf.core.geometry import utm_exception_key
from roadsurf.io import runfolder as rf
from roadsurf.io.drive import Drive
from roadsurf.io.runfolder import RunFolder
from roadsurf.mapping.config import NOT_IN_FINGERPRINT, MappingConfig
from roadsurf.mapping.datum import vertical_datum
from roadsurf.mapping.export import write_trajectory_csv, write_trajectory_geojson
from roadsurf.mapping.gps_consensus import altitude_keep, consensus_keep
from roadsurf.mapping.grade import GRADE_VERSION, road_grade
from roadsurf.mapping.mount import resolve
from roadsurf.mapping.plausibility import CHECKS_VERSION, check, frame_span, make_chains
from roadsurf.mapping.pose_gps import (
    GpsFixes,
    gps_enu,
    gps_margin_s,
    interp_weights,
    refix_antenna,
    widen_for_turns,
)
from roadsurf.mapping.pose_graph import PoseGraph
from roadsurf.mapping.pose_init import chain, initial_poses, segments
from roadsurf.mapping.separate import keep_apart, segment_has_gps
from roadsurf.mapping.types import PoseReport, Trajectory, load_trajectory, save_trajectory
from roadsurf.reconstruction.types import STATUS_NO_MOTION

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

# the trajectory's own version, in the stage's fingerprint (a resumed run recomputes after a
# change): 2: the ENU origin at the fix nearest the middle frame (was the log's first fix), a
# stopped vehicle's frames (no_motion pairs) held together in the pose graph and the bundle;
# 3: the mount's direction of travel turned back by half of each pair's turn (mount.heading_at_a);
# 4: fixes off their window's consensus left out of the first solve (mapping.gps_consensus)
POSES_VERSION = 4
# the antenna's fixes are moved with the solved rotations and solved again at most this many
# times, until no fix moves by ANTENNA_SETTLED_M (m)
ANTENNA_PASSES = 6
ANTENNA_SETTLED_M = 0.001

# =========================================================================== entry point


def run(
    cfg: MappingConfig,
    drive: Drive,
    pairs: list[PairResult],
    run_dir: str | Path,
    *,
    loop_match: Callable[[int, int], PairResult | None] | None = None,
) -> Trajectory:
    """Fuse GPS and pairs into the trajectory; writes RUN/poses.npz, reference.json,
    trajectory.geojson and poses_report.json. Resumes when the inputs did not change.
    loop_match: as ``estimate_trajectory`` (revisits; ``mapping.loops.frame_matcher``)."""
    run = RunFolder(run_dir)
    order = "retrieval" if getattr(loop_match, "score", None) is not None else "gps"
    key = _fingerprint(cfg, drive, pairs, loops=order if loop_match is not None else "")
    rep_path = run.path(rf.POSES_REPORT)
    geojson = run.path(rf.TRAJECTORY_GEOJSON)
    if not cfg.overwrite and run.poses_npz.is_file() and rep_path.is_file():
        try:
            if read_json_object(rep_path).get("fingerprint") == key:
                log.info("poses: inputs unchanged, reusing %s", run.poses_npz)
                traj = load_trajectory(run.root)
                if not geojson.is_file():
                    datum = vertical_datum(cfg, drive, traj.reference is not None)
                    write_trajectory_geojson(geojson, traj, drive, vertical_datum=datum)
                return traj
        except UNREADABLE as e:
            log.warning("poses: cached result unreadable (%s); recomputing", e)
    # the record goes first: a run stopped while rewriting leaves no record of the old poses
    # beside new files (a resume would trust them)
    rep_path.unlink(missing_ok=True)
    t0 = time.perf_counter()
    traj, report = estimate_trajectory(cfg, drive, pairs, loop_match=loop_match)
    save_trajectory(run.root, traj)
    write_trajectory_geojson(geojson, traj, drive, vertical_datum=report.vertical_datum)
    write_trajectory_csv(run.path(rf.TRAJECTORY_CSV), traj)
    elapsed = round(time.perf_counter() - t0, 3)  # kept for resumed runs' report.json
    write_json_atomic(rep_path, {"fingerprint": key, "elapsed_s": elapsed, **report.to_dict()})
    return traj


def _fingerprint(
    cfg: MappingConfig, drive: Drive, pairs: list[PairResult], *, loops: str = ""
) -> str:
    """What the trajectory depends on (a fixed byte stream): the config, the frames' names and
    times, the GPS fixes (time, lat, lon, altitude, HDOP), the OBD speeds, every pair's
    transform, whether revisits are matched (``loops``), the version of the plausibility
    checks whose warnings the report keeps and, with the bundle adjustment on, its version."""
    fp = Fingerprint()
    if loops:  # how the candidates are ordered: "retrieval" (image retrieval) or "gps"
        fp.add_text(f"loops:{loops}")
    if cfg.bundle_adjust:
        from roadsurf.mapping.bundle import BUNDLE_VERSION

        fp.add_text(f"bundle:{BUNDLE_VERSION}")
    fp.add_json({k: v for k, v in to_dict(cfg).items() if k not in NOT_IN_FINGERPRINT})
    fp.add_json([(f.filename, f.timestamp_s) for f in drive.frames], default_str=False)
    fp.add_text(f"mount:{drive.camera.mount_deg}")
    if drive.camera.gps_antenna_m is not None:
        fp.add_text(f"antenna:{drive.camera.gps_antenna_m}")
    if drive.gps is not None:
        g = drive.gps
        for a in (g.timestamp_s, g.lat_deg, g.lon_deg, g.hdop):
            fp.add_array(a)
        if cfg.gps_sigma_from_log and g.states_accuracy:  # else unused: keep the key
            fp.add_text("accuracy").add_array(g.sigma_m).add_array(g.quality)
        fp.add_text("alt").add_array(g.alt_m)
        fp.add_text(f"datum:{vertical_datum(cfg, drive)}")
        if len(g) and (
            utm := utm_exception_key(float(np.median(g.lat_deg)), float(np.median(g.lon_deg)))
        ):
            fp.add_text(utm)
    if drive.obd is not None:
        fp.add_text("obd").add_array(drive.obd.timestamp_s).add_array(drive.obd.speed_mps)
    for p in pairs:
        fp.add_text(f"{p.index_a},{p.index_b},{p.status}")
        fp.add_array(p.cam_b_from_cam_a)
    fp.add_text(f"checks:{CHECKS_VERSION}")
    fp.add_text(f"grade:{GRADE_VERSION}")
    fp.add_text(f"poses:{POSES_VERSION}")
    return fp.hexdigest(16)


def _at_rest(p: PairResult) -> PairResult:
    """A ``no_motion`` pair as the motion it stands for: none (R = I, t = 0)."""
    return dataclasses.replace(p, R_b_from_a=np.eye(3), t_b_from_a_m=np.zeros(3))


def estimate_trajectory(
    cfg: MappingConfig,
    drive: Drive,
    pairs: list[PairResult],
    *,
    loop_match: Callable[[int, int], PairResult | None] | None = None,
) -> tuple[Trajectory, PoseReport]:
    """Pure computation (no files): fused Trajectory and a PoseReport.

    loop_match(i, j): the pair API on the frames at positions i and j (revisits, issue 30):
    with it, frames the pose graph placed within ``bundle_loop_gate_m`` of each other at least
    ``bundle_loop_min_gap_s`` apart are matched, and the confirmed pairs close the loop."""
    frames = drive.frames
    n = len(frames)
    rep = PoseReport(n_frames=n)
    if n == 0:
        raise ValueError("roadsurf.mapping.poses: the drive has no valid frame to place")
    t = np.array([f.timestamp_s for f in frames], float)
    pos_of = {f.index: i for i, f in enumerate(frames)}
    ok_pairs = [p for p in pairs if p.ok and p.index_a in pos_of and p.index_b in pos_of]
    rep.n_pairs_ok = len(ok_pairs)
    rep.n_pairs_failed = sum(1 for p in pairs if not p.ok)
    consecutive = {(pos_of[p.index_a], pos_of[p.index_b]): p for p in ok_pairs}
    # consecutive frames a stopped vehicle took: the same place (R = I, t = 0), not a gap
    still = [
        _at_rest(p) for p in pairs
        if p.status == STATUS_NO_MOTION and p.index_a in pos_of and p.index_b in pos_of
        and pos_of[p.index_b] == pos_of[p.index_a] + 1
    ]  # fmt: skip
    rep.n_pairs_still = len(still)
    linked = consecutive | {(pos_of[p.index_a], pos_of[p.index_b]): p for p in still}

    # ---------------------------------------------------------------- GPS in ENU
    ref, gps = gps_enu(cfg, drive, t, rep)
    if gps is not None:
        ends = [
            (pos_of[p.index_a], p) for p in ok_pairs if pos_of[p.index_b] == pos_of[p.index_a] + 1
        ]
        gps = widen_for_turns(cfg, gps, t, ends)

    # ---------------------------------------------------------------- visual components
    comp = np.zeros(n, int)
    for i in range(1, n):
        comp[i] = comp[i - 1] + (0 if (i - 1, i) in linked else 1)

    def grade_and_mount(fixes: GpsFixes | None) -> tuple[np.ndarray, np.ndarray, list[str]]:
        grade = road_grade(
            t,
            fixes,
            window_m=cfg.grade_window_m,
            vertical_factor=cfg.gps_vertical_sigma_factor,
            prior_sigma_rad=math.atan(cfg.grade_sigma_pct / 100.0),
        )
        mount = resolve(
            drive.camera,
            ok_pairs,
            estimate=cfg.estimate_mount,
            disagree_deg=cfg.mount_disagree_deg,
            min_pitch_deg=cfg.mount_min_pitch_deg,
            grade_known=grade.mean_shrink(),
        )
        rep.mount = mount.to_dict()
        rep.mount.update(grade.to_dict())
        # roll is not observable from a camera and GPS: the map is placed for this cross-fall,
        # and each 1 % the road differs by moves it this far sideways (the rig turns about the
        # antenna, which the fixes hold: the camera's height plus the antenna's above it)
        arm = drive.camera.gps_antenna_m
        lever = drive.camera.height_m + (float(arm[2]) if arm is not None else 0.0)
        rep.mount["cross_fall_pct_assumed"] = cfg.cross_fall_pct
        rep.mount["sideways_m_per_pct_cross_fall"] = round(0.01 * lever, 4)
        return mount.R_vehicle_from_cam, grade.grade_rad, mount.warnings

    R_vc, g_rad, mount_warnings = grade_and_mount(gps)
    rep.warnings += mount_warnings
    # runs of fixes off the chained motion's local consensus (a multipath step) are left out
    # of the first solve, and of the grade and the initial placement
    keep = None
    if gps is not None and len(gps.t_s):
        chain_xyz = [
            chain(np.flatnonzero(comp == c), linked, R_vc)[:, :3, 3]
            for c in range(int(comp.max()) + 1)
        ]
        margin = gps_margin_s(cfg, t)
        alt_ok = altitude_keep(t, comp, chain_xyz, gps, margin)
        if not alt_ok.all():
            # heights only: a vertical jump leaves the fix's horizontal position usable
            bad = np.flatnonzero(~alt_ok)
            k = np.clip(np.searchsorted(t, gps.t_s[bad]), 0, n - 1)
            msg = (
                f"{len(bad)} GPS altitude(s) jump (by more than 0.3 m and 6 times the other "
                "fixes' scatter) where the frames show no such rise, near "
                f"{frame_span([f.filename for f in frames], int(k.min()), int(k.max()))}: their heights are left out "
                "(the map's heights and grade rest on the others)"
            )
            log.warning("poses: %s", msg)
            rep.warnings.append(msg)
            gps = dataclasses.replace(gps, has_alt=gps.has_alt & alt_ok)
            R_vc, g_rad, again = grade_and_mount(gps)
            rep.warnings += [w for w in again if w not in mount_warnings]
        chain_xy = [c[:, :2] for c in chain_xyz]

        def off_consensus(g: GpsFixes) -> np.ndarray | None:
            """The fixes to keep (None: all) by ``gps_consensus.consensus_keep``."""
            k = consensus_keep(t, comp, chain_xy, g, margin, cfg.heading_min_baseline_m)
            return None if k.all() else k

        keep = off_consensus(gps)
        if keep is not None:
            log.info("poses: %d GPS fix(es) off the visual consensus", int((~keep).sum()))
            R_vc, g_rad, again = grade_and_mount(gps.subset(keep))
            rep.warnings += [w for w in again if w not in mount_warnings]
    init = initial_poses(cfg, t, comp, linked, gps if keep is None else gps.subset(keep), rep, R_vc)

    # ---------------------------------------------------------------- segments
    segment, bridged_gaps = segments(t, comp, gps, cfg.gps_bridge_s)
    rep.n_segments = int(segment.max()) + 1
    if rep.n_segments > 1:
        msg = (
            f"{rep.n_segments - 1} break(s) where neither a matched pair nor GPS ties consecutive "
            "frames; segments are placed by a constant-velocity guess"
        )
        log.warning("poses: %s", msg)
        rep.warnings.append(msg)

    # ---------------------------------------------------------------- robust fusion
    problem = PoseGraph(
        cfg, t, init, ok_pairs, pos_of, gps, drive, comp, R_vc, g_rad, still, gps_used=keep
    )
    world = problem.solve(rep)
    if gps is not None and rep.gps_outliers:
        # The grade was fitted on every fix before the fusion found some wrong: a fix moved
        # metres sideways lengthens the track the heights are measured along and flattens the
        # slope (3 fixes moved 6 m: 0.16° kept of 0.45°, the camera 0.3° off in pitch). Fit it
        # again on the fixes kept, and solve again with it.
        R_vc, g_rad, again = grade_and_mount(gps.subset(problem.gps_used))
        rep.warnings += [w for w in again if w not in mount_warnings]
        # every fix judged again from the start (a frozen receiver: its σ inflated, not 14 of
        # 19 fixes rejected and 5 kept pinning the drive), except those off the consensus
        init = initial_poses(
            cfg, t, comp, linked, gps if keep is None else gps.subset(keep), rep, R_vc
        )
        problem = PoseGraph(
            cfg, t, init, ok_pairs, pos_of, gps, drive, comp, R_vc, g_rad, still, gps_used=keep
        )
        world = problem.solve(rep)
    if gps is not None and ref is not None and drive.camera.gps_antenna_m is not None:
        # the antenna's fixes moved again with the solved vehicle heading, until they settle:
        # its own track's direction is the heading only over the point of the vehicle that does
        # not slide, and each solve inherits part of that error (an 11 m curve, arm 1.5 m
        # behind: trajectory RMSE 36.8 mm after one more solve, 27.8 mm settled)
        for _ in range(ANTENNA_PASSES):
            moved = refix_antenna(gps, drive, ref, t, world, R_vc)
            step = float(np.max(np.linalg.norm(moved.enu_m - gps.enu_m, axis=1), initial=0.0))
            gps = moved
            if step < ANTENNA_SETTLED_M:
                break
            # judged again on the fixes moved with the solved heading (the first pass's track
            # heading is poor at the log's ends and on curves)
            keep = off_consensus(gps)
            problem = PoseGraph(
                cfg, t, world, ok_pairs, pos_of, gps, drive, comp, R_vc, g_rad, still,
                gps_used=keep,
            )  # fmt: skip
            world = problem.solve(rep)
    has_gps = segment_has_gps(segment, t, None if gps is None else gps.t_s)
    names = [f.filename for f in frames]
    world, warns = keep_apart(world, segment, pairs, pos_of, drive.camera, names, has_gps=has_gps)
    rep.warnings += warns
    if loop_match is not None and cfg.bundle_loop_gate_m > 0:  # issue 30: revisits
        from roadsurf.mapping.loops import confirm_loops, loop_candidates

        cand = loop_candidates(
            t, world[:, :3, 3], gate_m=cfg.bundle_loop_gate_m, min_gap_s=cfg.bundle_loop_min_gap_s
        )
        score = getattr(loop_match, "score", None)  # image retrieval, when the matcher has it
        if score is not None:
            from roadsurf.mapping.retrieval import rank_candidates

            cand = rank_candidates(cand, score)
        loops = confirm_loops(cand, loop_match)
        rep.bundle["loops"] = [[pos_of[p.index_a], pos_of[p.index_b]] for p in loops]
        if loops:
            problem = PoseGraph(
                cfg, t, world, ok_pairs + loops, pos_of, gps, drive, comp, R_vc, g_rad, still,
                gps_used=keep,
            )  # fmt: skip
            world = problem.solve(rep)
    else:
        loops = []
    if cfg.bundle_adjust:  # issue 30: the pose graph's poses are the initial guess
        from roadsurf.mapping.bundle import refine_poses, with_motions_of

        world, bundle = refine_poses(
            cfg, drive, t, world, ok_pairs, pos_of, gps, problem.gps_used, R_vc, g_rad, still
        )
        rep.bundle.update(bundle)
        if loops:
            # the windows hold no loop constraint: one more pose-graph pass over the bundle's
            # frame-to-frame motions and the loop pairs puts the passes back together
            refined = with_motions_of(ok_pairs, pos_of, world) + loops
            problem = PoseGraph(
                cfg, t, world, refined, pos_of, gps, drive, comp, R_vc, g_rad, still,
                gps_used=keep,
            )  # fmt: skip
            world = problem.solve(rep)

    # ---------------------------------------------------------------- plausibility
    if gps is not None:
        chains = make_chains(
            cfg,
            comp,
            {k: p.cam_b_from_cam_a[:3, 3] for k, p in linked.items()},
            lambda fr: chain(fr, linked, R_vc),
        )

        def errors_m() -> np.ndarray:
            k, w = interp_weights(t, gps.t_s)
            k1 = np.minimum(k + 1, n - 1)
            pred = (1 - w)[:, None] * world[k, :3, 3] + w[:, None] * world[k1, :3, 3]
            return np.linalg.norm(pred[:, :2] - gps.enu_m[:, :2], axis=1)

        warns, rep.checks = check(
            cfg, drive, t, chains, gps, ref, problem.gps_used, problem.gps_scale, errors_m
        )
        for w in warns:
            log.warning("poses: %s", w)
        rep.warnings += warns
    rep.vertical_datum = vertical_datum(cfg, drive, ref is not None)

    # ---------------------------------------------------------------- sources
    has_visual = np.zeros(n, bool)
    for a, b in linked:
        has_visual[a] = has_visual[b] = True
    gps_comp = set()
    if gps is not None:
        for g_t in gps.t_s[problem.gps_used]:
            k = int(np.clip(np.searchsorted(t, g_t), 0, n - 1))
            gps_comp.add(comp[k])
            if k > 0:
                gps_comp.add(comp[k - 1])
    source = []
    for i in range(n):
        tied = comp[i] in gps_comp
        if has_visual[i]:
            source.append("fused" if tied else "visual")
        else:
            source.append("gps" if gps is not None else "visual")
    traj = Trajectory(
        filenames=[f.filename for f in frames],
        frame_indices=np.array([f.index for f in frames], np.int64),
        timestamp_s=t,
        world_from_cam=world,
        source=source,
        reference=ref,
        segment=segment,
        vehicle_from_cam=R_vc,
    )
    del bridged_gaps
    return traj, rep
