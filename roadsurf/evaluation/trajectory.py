"""Trajectory figures of a run against simulator truth: horizontal RMSE (raw and after a 2D
rigid alignment), relative drift over 5 m windows, and the GPS fixes' own error."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.errors import InputError
from roadsurf.core.fits import fit_rigid_2d
from roadsurf.core.geometry import vehicle_from_cam_rotation, vehicle_from_flu
from roadsurf.io import drivefolder as df
from roadsurf.io import runfolder as rf
from roadsurf.io.formats import read_csv, read_geojson

log = logging.getLogger(__name__)


def truth_poses(truth_dir: Path) -> dict[str, Any]:
    rows = read_csv(truth_dir / df.TRUTH_POSES_CSV)
    return {
        "filename": [r["filename"] for r in rows],
        "xy": np.array([[float(r["easting_m"]), float(r["northing_m"])] for r in rows]),
        "up": np.array([float(r["up_m"]) for r in rows]),
        "q": np.array([[float(r[k]) for k in ("qw", "qx", "qy", "qz")] for r in rows]),
        "heading_deg": np.array([float(r["heading_deg"]) for r in rows]),
        # the frames' (first rows') times: a rolling shutter's later rows from the motion
        "t": np.array([float(r.get("timestamp_s") or "nan") for r in rows]),
    }


def truth_rotations(truth: dict[str, Any]) -> np.ndarray:
    """(N, 3, 3) world_from_cam rotations (grid axes) of ``truth_poses``' quaternions."""
    from scipy.spatial.transform import Rotation

    q = truth["q"]  # (N, 4) w, x, y, z
    return np.asarray(Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix())


def run_trajectory(run_dir: Path, crs: str | None) -> dict[str, Any] | None:
    path = run_dir / rf.TRAJECTORY_GEOJSON
    if not path.is_file() or crs is None:
        return None
    from pyproj import Transformer

    fc = read_geojson(path)
    names, ll, hd = [], [], []
    for f in fc["features"]:
        if f["geometry"]["type"] == "Point" and "filename" in f["properties"]:
            names.append(f["properties"]["filename"])
            ll.append(f["geometry"]["coordinates"][:2])
            hd.append(float(f["properties"].get("heading_deg", float("nan"))))
    if not names:
        return None
    ll_a = np.array(ll, float)
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(ll_a[:, 0], ll_a[:, 1])
    return {"filename": names, "xy": np.column_stack([x, y]), "heading_deg": np.array(hd)}


def trajectory_metrics(est: dict[str, Any], truth: dict[str, Any]) -> dict[str, Any]:
    idx = {n: i for i, n in enumerate(truth["filename"])}
    pairs = [(i, idx[n]) for i, n in enumerate(est["filename"]) if n in idx]
    if len(pairs) < 2:
        ex = ", ".join(est["filename"][:2]) or "none"
        tx = ", ".join(truth["filename"][:2]) or "none"
        raise InputError(
            f"{len(pairs)} of the run's {len(est['filename'])} frames have a row in the truth's "
            f"poses.csv (run: {ex}, ...; truth: {tx}, ...): evaluate a run of this drive, and "
            "keep the frames' file names (the truth is matched by name)"
        )
    e = est["xy"][[a for a, _ in pairs]]
    t = truth["xy"][[b for _, b in pairs]]
    err = np.linalg.norm(e - t, axis=1)
    fit = fit_rigid_2d(e, t)
    R, tr = fit.R, fit.t
    ea = e @ R.T + tr
    err_a = np.linalg.norm(ea - t, axis=1)
    # relative drift (relative pose error): the displacement over windows of 5 m of true travel,
    # each expressed in its own vehicle frame (heading). A rotation shared by the positions and
    # the headings cancels (UTM grid north vs true north too); an offset of the headings alone
    # counts in full: a mount yaw error of e rad reads as e x 100 % drift.
    he = np.radians(est["heading_deg"][[a for a, _ in pairs]])
    ht = np.radians(truth["heading_deg"][[b for _, b in pairs]])
    if not np.all(np.isfinite(he)):
        he = ht  # a producer without headings: world-frame displacements
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(t, axis=0), axis=1))])
    drift = []
    for i in range(len(s)):
        j = int(np.searchsorted(s, s[i] + 5.0))
        if j >= len(s):
            break
        d_true = _body(t[j] - t[i], ht[i])
        d_est = _body(e[j] - e[i], he[i])
        drift.append(np.linalg.norm(d_est - d_true) / max(s[j] - s[i], 1e-9) * 100.0)
    drift_a = np.array(drift)
    if not drift:
        log.info("drive shorter than 5 m: no relative drift figure")
    dstat = (
        (float(np.median(drift_a)), float(np.percentile(drift_a, 95)), float(np.max(drift_a)))
        if drift
        else (float("nan"),) * 3
    )
    rv = revisit_agreement(e, t)
    metrics = {
        "n_frames_matched": len(pairs),
        "trajectory_rmse_m": float(np.sqrt(np.mean(err**2))),
        "trajectory_max_m": float(err.max()),
        "trajectory_rmse_aligned_m": float(np.sqrt(np.mean(err_a**2))),
        "alignment_offset_m": float(np.linalg.norm(tr + (R - np.eye(2)) @ e.mean(0))),
        "alignment_rotation_deg": float(math.degrees(math.atan2(R[1, 0], R[0, 0]))),
        "drift_5m_median_pct": dstat[0],
        "drift_5m_p95_pct": dstat[1],
        "drift_5m_max_pct": dstat[2],
        "distance_m": float(s[-1]),
        "revisit_pairs": rv[0],
        "revisit_agreement_m": rv[1],
        "revisit_agreement_max_m": rv[2],
    }
    return {"metrics": metrics, "align": (R, tr)}


# frames of two passes count as the same place within this horizontal distance (m) when the
# drive travelled at least REVISIT_MIN_TRAVEL_M between them (not a stop, a pass that came back)
REVISIT_NEAR_M = 0.25
REVISIT_MIN_TRAVEL_M = 5.0


def revisit_agreement(est_xy: np.ndarray, true_xy: np.ndarray) -> tuple[int, float, float]:
    """How well two passes over the same place agree (issue 30's loop closure): for each frame
    j and the earlier frame i nearest to it in the truth (within ``REVISIT_NEAR_M``, after at
    least ``REVISIT_MIN_TRAVEL_M`` of true travel), the error of the estimated offset between
    them, |(e_j - e_i) - (t_j - t_i)| (m, horizontal). est_xy, true_xy: (N, 2) matched frames
    in drive order. Returns (number of such pairs, median, max); (0, nan, nan) without a
    revisit. Independent of any global offset or of the GPS: only the passes' agreement."""
    n = len(true_xy)
    if n < 2:
        return 0, float("nan"), float("nan")
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(true_xy, axis=0), axis=1))])
    errs = []
    for j in range(n):
        early = np.flatnonzero(s <= s[j] - REVISIT_MIN_TRAVEL_M)
        if not len(early):
            continue
        d = np.linalg.norm(true_xy[early] - true_xy[j], axis=1)
        k = int(np.argmin(d))
        if d[k] > REVISIT_NEAR_M:
            continue
        i = int(early[k])
        errs.append(np.linalg.norm((est_xy[j] - est_xy[i]) - (true_xy[j] - true_xy[i])))
    if not errs:
        return 0, float("nan"), float("nan")
    return len(errs), float(np.median(errs)), float(np.max(errs))


def _body(d: np.ndarray, heading_rad: float) -> np.ndarray:
    """World (E, N) displacement -> vehicle frame (right, forward) for a compass heading."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    return np.array([d[0] * c - d[1] * s, d[0] * s + d[1] * c])


def gps_rmse_m(
    truth_dir: Path,
    crs: str | None,
    antenna_flu: tuple[float, float, float] | None = None,
    mount_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> float | None:
    """RMSE (m, horizontal) of the drive's GPS fixes against the true path of the antenna
    interpolated at the fix times: the camera centre plus ``antenna_flu`` ([forward, left, up]
    m, the simulator's ``gps_antenna_m``) on the vehicle, turned by each true camera rotation
    (the poses' quaternion, grid axes) back through the mount ``mount_deg`` (pitch, roll, yaw;
    the simulator's ``mount_*_deg``). Without it a lever arm counts as GPS error (1.5 m on a
    drive whose antenna rides 1.5 m behind the camera)."""
    gps = truth_dir.parent / df.GPS_CSV
    if crs is None or not gps.is_file():
        return None
    from pyproj import Transformer

    tp = truth_poses(truth_dir)
    tt, txy = tp["t"], tp["xy"]
    g = read_csv(gps)
    try:
        t = np.array([float(r["timestamp_s"]) for r in g])
        lat = np.array([float(r["lat"]) for r in g])
        lon = np.array([float(r["lon"]) for r in g])
    except (KeyError, ValueError):
        return None
    inside = (t >= tt[0]) & (t <= tt[-1])
    if not inside.any():
        return None
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(
        lon[inside], lat[inside]
    )
    if antenna_flu is not None and any(antenna_flu):
        R_vc = vehicle_from_cam_rotation(*mount_deg)
        arm = truth_rotations(tp) @ R_vc.T @ vehicle_from_flu(antenna_flu)
        txy = txy + arm[:, :2]
    ex = np.interp(t[inside], tt, txy[:, 0])
    ey = np.interp(t[inside], tt, txy[:, 1])
    return float(np.sqrt(np.mean((np.asarray(x) - ex) ** 2 + (np.asarray(y) - ey) ** 2)))


def gps_noise_m(truth_dir: Path, scen: dict[str, Any]) -> float | None:
    g = scen.get("derived", {}).get("gps", {})
    if isinstance(g, dict) and g.get("sigma_m"):
        return float(g["sigma_m"])
    p = scen.get("params", {})
    for k in ("gps_sigma_m", "gps_noise_m", "gps_sigma"):
        if k in p and p[k]:
            return float(p[k])
    return None
