"""GPS preprocessing for the pose graph: fixes in ENU with their σ, the fixes usable as
measurements (inside the frame time span or just outside its ends), and the GPS track
interpolated at any time."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from roadsurf.core.geometry import EnuReference, enu_from_lla
from roadsurf.io.drive import Drive, GpsTrack
from roadsurf.io.drive.types import NO_GEOREF
from roadsurf.mapping.antenna import cam_from_antenna, cam_from_antenna_posed
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.mount import turn_about_rad
from roadsurf.mapping.types import PoseReport
from roadsurf.reconstruction.consensus import plane_normal_cam
from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


@dataclass
class GpsFixes:
    """The GPS fixes used as measurements, in the local ENU frame."""

    t_s: np.ndarray  # (G,)
    enu_m: np.ndarray  # (G, 3)
    sigma_m: np.ndarray  # (G,) horizontal σ
    has_alt: np.ndarray  # (G,) bool
    orig_index: np.ndarray  # (G,) index into drive.gps

    def subset(self, idx: np.ndarray) -> GpsFixes:
        """The fixes at ``idx`` (a (G,) bool mask or an index array)."""
        return GpsFixes(
            self.t_s[idx], self.enu_m[idx], self.sigma_m[idx], self.has_alt[idx],
            self.orig_index[idx],
        )  # fmt: skip


def gps_enu(
    cfg: MappingConfig, drive: Drive, t: np.ndarray, rep: PoseReport
) -> tuple[EnuReference | None, GpsFixes | None]:
    g = drive.gps
    if g is None or len(g) == 0:
        msg = "no GPS: the map is in a local frame (no reference, no lat/lon or UTM exports)"
        if any(NO_GEOREF in w for w in drive.warnings):  # the loader said it, and why
            log.info("poses: %s", msg)
        else:
            log.warning("poses: %s", msg)
            rep.warnings.append(msg)
        return None, None
    rep.n_gps_fixes = len(g)
    alt = np.asarray(g.alt_m, float)
    has_alt = np.isfinite(alt)
    ref = enu_reference(g, t)
    enu = antenna_enu(g, ref)
    sigma = sigma_fix = fix_sigma_m(cfg, g)
    # fixes usable as measurements: inside the frame time span, or close enough to its ends
    # for the end frames' constant-velocity extrapolation (σ inflated by the acceleration)
    margin = gps_margin_s(cfg, t)
    ts = np.asarray(g.timestamp_s, float)
    keep = (ts >= t[0] - margin) & (ts <= t[-1] + margin)
    outside_s = np.maximum(np.maximum(t[0] - ts, ts - t[-1]), 0.0)
    sigma = np.hypot(sigma, 0.5 * cfg.gap_accel_sigma_mps2 * outside_s**2)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        msg = "GPS does not overlap the frame times: local frame only"
        log.warning("poses: %s", msg)
        rep.warnings.append(msg)
        return None, None
    if drive.camera.gps_antenna_m is not None:  # only the fixes used: a log may span hours
        arm = np.asarray(drive.camera.gps_antenna_m)
        enu[idx] = cam_from_antenna(enu[idx], sigma_fix[idx], has_alt[idx], arm)
    gps = GpsFixes(
        t_s=np.asarray(g.timestamp_s, float)[idx],
        enu_m=enu[idx],
        sigma_m=sigma[idx],
        has_alt=has_alt[idx] & cfg.use_gps_altitude,
        orig_index=idx,
    )
    return ref, gps


def antenna_enu(g: GpsTrack, ref: EnuReference, idx: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) the log's fixes (those at ``idx``, None = all) in the local ENU frame ``ref`` (m),
    as logged (the antenna's); a fix without altitude at the reference's."""
    sel = slice(None) if idx is None else idx
    alt = np.asarray(g.alt_m, float)[sel]
    alt = np.where(np.isfinite(alt), alt, ref.alt_m)
    return enu_from_lla(np.asarray(g.lat_deg)[sel], np.asarray(g.lon_deg)[sel], alt, ref)


def refix_antenna(
    gps: GpsFixes,
    drive: Drive,
    ref: EnuReference,
    t: np.ndarray,
    world_from_cam: np.ndarray,
    R_vehicle_from_cam: np.ndarray,
) -> GpsFixes:
    """The fixes moved from the antenna onto the camera centre again, now with the vehicle's
    rotation from the solved poses (``antenna.cam_from_antenna_posed``); unchanged without
    camera.yaml's gps_antenna_m or GPS."""
    arm = drive.camera.gps_antenna_m
    if arm is None or drive.gps is None:
        return gps
    raw = antenna_enu(drive.gps, ref, gps.orig_index)
    enu = cam_from_antenna_posed(
        raw, gps.t_s, t, world_from_cam, R_vehicle_from_cam, np.asarray(arm)
    )
    return GpsFixes(gps.t_s, enu, gps.sigma_m, gps.has_alt, gps.orig_index)


def fix_sigma_m(cfg: MappingConfig, g: GpsTrack) -> np.ndarray:
    """(N,) horizontal σ per axis (m) of each fix: with ``gps_sigma_from_log`` the receiver's
    own (gps.csv 'sigma_m', NMEA GST), else by its fix quality when RTK
    (``gps_sigma_rtk_fixed_m`` / ``_float_m``); otherwise (the default) HDOP x
    ``gps_sigma_per_hdop_m``, else ``gps_sigma_m``; at least ``gps_sigma_min_m``."""
    hdop = np.asarray(g.hdop, float)
    sigma = np.where(np.isfinite(hdop), hdop * cfg.gps_sigma_per_hdop_m, cfg.gps_sigma_m)
    if not cfg.gps_sigma_from_log:
        if g.states_accuracy:
            log.info(
                "poses: %s states the fixes' accuracy (median σ %s, %d RTK fixed); weighing "
                "them by HDOP (mapping.gps_sigma_from_log: false, the default)",
                g.source, _median_text(g.sigma_m), int(np.sum(g.quality == 4)),
            )  # fmt: skip
        return np.maximum(sigma, cfg.gps_sigma_min_m)
    q = np.asarray(g.quality)
    sigma = np.where(q == 4, cfg.gps_sigma_rtk_fixed_m, sigma)
    sigma = np.where(q == 5, cfg.gps_sigma_rtk_float_m, sigma)
    stated = np.asarray(g.sigma_m, float)
    sigma = np.where(np.isfinite(stated), stated, sigma)
    return np.maximum(sigma, cfg.gps_sigma_min_m)


def _median_text(a: np.ndarray) -> str:
    v = np.asarray(a, float)
    v = v[np.isfinite(v)]
    return f"{float(np.median(v)):.3f} m" if v.size else "not given"


# consecutive pairs at each end of the drive whose turn sets the extrapolation's acceleration
END_PAIRS = 5
# fixes within the frames' span that make those beyond a turning end unnecessary (count)
MIN_INSIDE_FIXES = 5
# ... and the turn (lateral acceleration, m/s²) beyond which they are left out then: a 36 m
# radius at 6 m/s. The straight extrapolation's error is a bias every fix beyond that end
# shares, not noise (½·a·Δt²: 1.1 m at 1.5 s); the default route's gentle curves stay below
# 0.2 m/s²
TURN_ACCEL_MPS2 = 1.0


def widen_for_turns(
    cfg: MappingConfig, gps: GpsFixes, t: np.ndarray, pairs: list[tuple[int, PairResult]]
) -> GpsFixes:
    """The fixes outside the frames' span (``gps_extrapolate_s``) at an end that turns: a =
    θ·|t| / Δt_pair², the median of the ``END_PAIRS`` consecutive ``pairs`` ((position of frame
    a, pair)) there (θ the pair's turn about its road normal, |t| its metric baseline). The end
    frames are extrapolated on a straight line, and in a turn the road bends away from it (an
    S-curve at 6.6 m/s², half a second out: 0.8 m, a bias, not noise). With
    ``MIN_INSIDE_FIXES`` fixes within the frames they are dropped beyond ``TURN_ACCEL_MPS2``
    (they pulled an RTK drive's whole trajectory 10-14 cm off its fixes; widening their σ by
    ½·a·Δt² left 9-10 cm); else (a short drive resting on its few fixes) their σ is widened by
    ½·a·Δt² when a beats ``gap_accel_sigma_mps2``."""
    if len(t) < 2 or not pairs:
        return gps
    a0 = float(cfg.gap_accel_sigma_mps2)
    sig = gps.sigma_m.copy()
    keep = np.ones(len(sig), bool)
    n_inside = int(np.sum((gps.t_s >= t[0]) & (gps.t_s <= t[-1])))
    for side in (0, 1):
        ts = gps.t_s
        out_s = (t[0] - ts) if side == 0 else (ts - t[-1])
        sel = out_s > 0
        if not sel.any():
            continue
        ordered = sorted(pairs, key=lambda q: q[0], reverse=side == 1)[:END_PAIRS]
        acc = []
        for k, p in ordered:
            dt = float(t[k + 1] - t[k])  # consecutive frames
            theta = _yaw_rad(p)
            if dt > 0:
                acc.append(theta * float(np.linalg.norm(p.t_b_from_a_m)) / dt**2)
        a = float(np.median(acc)) if acc else 0.0
        drop = n_inside >= MIN_INSIDE_FIXES and a > TURN_ACCEL_MPS2
        if not drop and a <= a0:
            continue
        if drop:
            keep &= ~sel
        else:
            d = out_s[sel]
            base2 = np.maximum(sig[sel] ** 2 - (0.5 * a0 * d**2) ** 2, 0.0)
            sig[sel] = np.sqrt(base2 + (0.5 * a * d**2) ** 2)
        log.info(
            "poses: the %s pairs turn at %.1f m/s²: the %d fixes %s the frames are %s",
            "first" if side == 0 else "last", a, int(sel.sum()),
            "before" if side == 0 else "after", "not used" if drop else "widened by it",
        )  # fmt: skip
    out = GpsFixes(gps.t_s, gps.enu_m, sig, gps.has_alt, gps.orig_index)
    return out if keep.all() else out.subset(keep)


def _yaw_rad(p: PairResult) -> float:
    """|rotation| of the pair about its road normal (rad): its turn, without the vibration's
    roll and pitch (0.5-1° a frame, which read as 1-2 m/s² at 15 fps); the whole rotation
    without a plane."""
    pl = np.asarray(p.plane, float)
    if pl.shape != (3,) or not np.all(np.isfinite(pl)):
        return float(np.arccos(np.clip((np.trace(p.R_b_from_a) - 1.0) / 2.0, -1.0, 1.0)))
    return abs(turn_about_rad(p.R_b_from_a, plane_normal_cam(pl)))


def enu_reference(g: GpsTrack, t: np.ndarray) -> EnuReference:
    """The local ENU frame's origin: the GPS fix nearest in time to the drive's middle frame
    (``t`` (N,) frame times, s), at that fix's altitude (the nearest fix with one; 0 without).

    Not the log's first fix: a logger started at the depot puts that fix kilometres from the
    frames, where the tangent plane has left the road (d² / 2R: 0.8 m at 3.2 km) and a height
    of the road above the ellipsoid moves a cell sideways by h d / R (0.57 m at 1 km, 3,640 m
    up). From the middle, a drive of L metres stays within L / 2 of its origin."""
    ts = np.asarray(g.timestamp_s, float)
    mid = float(t[len(t) // 2]) if len(t) else float(ts[0])
    i = int(np.argmin(np.abs(ts - mid)))
    alt = np.asarray(g.alt_m, float)
    has_alt = np.flatnonzero(np.isfinite(alt))
    a = float(alt[has_alt[np.argmin(np.abs(has_alt - i))]]) if has_alt.size else 0.0
    return EnuReference(float(g.lat_deg[i]), float(g.lon_deg[i]), a)


def gps_margin_s(cfg: MappingConfig, t: np.ndarray) -> float:
    """How far (s) before the first frame / after the last a GPS fix is still used."""
    dt_frame = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    return max(0.5 * dt_frame, float(cfg.gps_extrapolate_s))


def interp_weights(t: np.ndarray, tq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For query times tq: index k of the frame before (k+1 after) and weight w of frame k+1."""
    n = len(t)
    if n == 1:
        return np.zeros(len(tq), int), np.zeros(len(tq))
    k = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, n - 2)
    w = (tq - t[k]) / np.maximum(t[k + 1] - t[k], 1e-9)
    return k, w


def gps_at(gps: GpsFixes, tq: float) -> np.ndarray:
    """(3,) GPS track at time tq: linear between fixes, extrapolated from the end pairs."""
    ts, p = gps.t_s, gps.enu_m
    if len(ts) == 1:
        return p[0].copy()
    k = int(np.clip(np.searchsorted(ts, tq) - 1, 0, len(ts) - 2))
    w = (tq - ts[k]) / max(ts[k + 1] - ts[k], 1e-9)
    return (1 - w) * p[k] + w * p[k + 1]


def gps_track_yaw(gps: GpsFixes, tc: float, min_base_m: float) -> float | None:
    """Counter-clockwise-from-east yaw of the GPS track around time tc (eq. 6.1 chord)."""
    order = np.argsort(np.abs(gps.t_s - tc))
    for j in order[1:]:
        d = gps.enu_m[j, :2] - gps.enu_m[order[0], :2]
        if np.linalg.norm(d) >= min_base_m:
            if gps.t_s[j] < gps.t_s[order[0]]:
                d = -d
            return math.atan2(d[1], d[0])
    return None
