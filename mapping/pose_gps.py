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
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.types import PoseReport

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
        log.warning("poses: %s", msg)
        rep.warnings.append(msg)
        return None, None
    rep.n_gps_fixes = len(g)
    alt = np.asarray(g.alt_m, float)
    has_alt = np.isfinite(alt)
    ref = enu_reference(g, t)
    alt0 = ref.alt_m
    enu = enu_from_lla(g.lat_deg, g.lon_deg, np.where(has_alt, alt, alt0), ref)
    hdop = np.asarray(g.hdop, float)
    sigma = np.where(np.isfinite(hdop), hdop * cfg.gps_sigma_per_hdop_m, cfg.gps_sigma_m)
    sigma = np.maximum(sigma, cfg.gps_sigma_min_m)
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
    gps = GpsFixes(
        t_s=np.asarray(g.timestamp_s, float)[idx],
        enu_m=enu[idx],
        sigma_m=sigma[idx],
        has_alt=has_alt[idx] & cfg.use_gps_altitude,
        orig_index=idx,
    )
    return ref, gps


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
