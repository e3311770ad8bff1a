"""Plausibility checks between the drive's inputs, where the loader has the data: GPS fixes that
jump impossibly far (hemisphere flip, UTM-zone jump), a static receiver, and OBD speed against
the GPS ground speed (including km/h written as m/s). Each finding is a warning with figures.

Distances are geodesic (pyproj ``Geod``, WGS84), so a flip to the other hemisphere measures right.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
from pyproj import Geod

from roadsurf.core.geometry import utm_zone_number
from roadsurf.io.drive.types import Frame, GpsTrack, ObdLog, Skipped

log = logging.getLogger(__name__)

V_MAX_MPS = 100.0  # faster than any road vehicle: a fix implying more is wrong
JUMP_SLACK_M = 50.0  # noise allowance, so close-spaced noisy fixes never trip the speed test
UERE_M = 3.0  # horizontal σ of a fix ≈ HDOP × UERE (consumer receiver)
SIGMA_NO_HDOP_M = 5.0  # σ of a fix when the log has no HDOP
STATIC_MIN_S = 5.0  # frames must span this long before a still GPS means something
STATIC_K = 3.0  # "within the noise": every fix within STATIC_K σ of the median position
OBD_WINDOW_S = 10.0  # GPS windows for the ground speed (noise shrinks with length)
# ... each also measured along the fixes this far apart in time (s): on a turn a window's chord
# is far shorter than the road driven (a U-turn of 40 m: 2.3x), a path through 1 s steps within
# 3 %; on a straight road with noisy fixes the chord is the right one (the steps add the noise)
OBD_STEP_S = 1.0
OBD_TOL = 0.25  # OBD / GPS speed ratio accepted within ±25 %
KMH_PER_MPS = 3.6
KMH_TOL = 0.15  # a ratio within ±15 % of 3.6 is km/h typed for m/s

_GEOD = Geod(ellps="WGS84")


def _dist_m(lat0: np.ndarray, lon0: np.ndarray, lat1: np.ndarray, lon1: np.ndarray) -> np.ndarray:
    """Geodesic distance (m) between (lat0, lon0) and (lat1, lon1), element-wise, degrees in."""
    _, _, d = _GEOD.inv(lon0, lat0, lon1, lat1)
    return np.atleast_1d(np.asarray(d, dtype=float))


def _jump_kind(lat0: float, lon0: float, lat1: float, lon1: float) -> str:
    if (lat0 < 0) != (lat1 < 0) or (lon0 < 0) != (lon1 < 0):
        return "hemisphere flip"
    if utm_zone_number(lon0) != utm_zone_number(lon1):
        return f"UTM zone jump {utm_zone_number(lon0)} -> {utm_zone_number(lon1)}"
    return "jump"


def fix_sigma_m(hdop: np.ndarray) -> float:
    """Horizontal σ (m) of one fix from the log's median HDOP."""
    h = np.asarray(hdop, float)
    h = h[np.isfinite(h) & (h > 0)]
    return float(np.median(h)) * UERE_M if h.size else SIGMA_NO_HDOP_M


def reject_jumps(
    path: Path,
    t: np.ndarray,
    lat: np.ndarray,
    lon: np.ndarray,
    lines: list[int | None],
    skipped: list[Skipped],
    warnings: list[str],
) -> np.ndarray:
    """(N,) bool mask of the fixes to keep. Times strictly increase. A step between consecutive
    fixes longer than ``V_MAX_MPS`` × dt + ``JUMP_SLACK_M`` is impossible; the longest run of
    fixes without such a step is trusted, and the fixes before and after it are kept only when
    they are reachable from the last kept fix. Rejected fixes are skipped and named."""
    n = len(t)
    keep = np.ones(n, dtype=bool)
    if n < 2:
        return keep
    step = _dist_m(lat[:-1], lon[:-1], lat[1:], lon[1:])
    bad = step > V_MAX_MPS * np.diff(t) + JUMP_SLACK_M
    if not bad.any():
        return keep
    starts = np.r_[0, np.flatnonzero(bad) + 1]
    ends = np.r_[starts[1:], n]
    k = int(np.argmax(ends - starts))
    s0, s1 = int(starts[k]), int(ends[k])
    keep[:] = False
    keep[s0:s1] = True

    def reachable(i: int, j: int) -> bool:
        d = float(_dist_m(lat[i : i + 1], lon[i : i + 1], lat[j : j + 1], lon[j : j + 1])[0])
        return d <= V_MAX_MPS * abs(float(t[j] - t[i])) + JUMP_SLACK_M

    ref = np.full(n, -1)  # the kept fix each rejected one was measured from
    last = s1 - 1
    for i in range(s1, n):
        if reachable(last, i):
            keep[i], last = True, i
        else:
            ref[i] = last
    first = s0
    for i in range(s0 - 1, -1, -1):
        if reachable(i, first):
            keep[i], first = True, i
        else:
            ref[i] = first
    names: list[str] = []
    for i in (int(k) for k in np.flatnonzero(~keep)):
        j = int(ref[i])
        d = float(_dist_m(lat[j : j + 1], lon[j : j + 1], lat[i : i + 1], lon[i : i + 1])[0])
        dt = abs(float(t[i] - t[j]))
        kind = _jump_kind(float(lat[j]), float(lon[j]), float(lat[i]), float(lon[i]))
        where = f"line {lines[i]}" if lines[i] is not None else f"fix #{i + 1}"
        what = (
            f"{kind}: ({lat[i]:.6f}, {lon[i]:.6f}) is {d / 1000:.1f} km from the fix at "
            f"{t[j]:.3f} s, {dt:.3f} s away ({d / max(dt, 1e-9):.0f} m/s)"
        )
        skipped.append(Skipped(path.name, lines[i], f"GPS fix rejected, {what}"))
        names.append(f"{where} at {t[i]:.3f} s ({what})")
    more = f"; and {len(names) - 3} more" if len(names) > 3 else ""
    warnings.append(
        f"{path}: rejected {len(names)} of {n} GPS fix(es) that imply a speed over "
        f"{V_MAX_MPS:.0f} m/s from their neighbours: {'; '.join(names[:3])}{more}. Check the "
        f"receiver log (sign of lat/lon, UTM zone of converted coordinates)."
    )
    return keep


# frames.csv's median interval may be this many times camera.yaml's 1 / fps either way before
# a warning (−): frames kept every k-th (distance-triggered or thinned) are normal; a factor
# of 1000 is milliseconds
FRAME_RATE_FACTOR = 20.0


def check_frame_rate(path: Path, frames: list[Frame], fps: float, warnings: list[str]) -> None:
    """Warn when frames.csv's median frame interval and camera.yaml's ``fps`` disagree by more
    than ``FRAME_RATE_FACTOR`` (timestamps in ms or µs, or a wrong fps)."""
    t = np.array([f.timestamp_s for f in frames], float)
    if len(t) < 2 or fps <= 0:
        return
    dt = float(np.median(np.diff(t)))
    if dt <= 0:
        return
    ratio = dt * fps
    if 1.0 / FRAME_RATE_FACTOR <= ratio <= FRAME_RATE_FACTOR:
        return
    unit = " (milliseconds? timestamp_s is in seconds)" if 300 <= ratio <= 3000 else ""
    warnings.append(
        f"{path}: the median frame interval is {dt:.4g} s, {ratio:.3g}x camera.yaml's 1 / fps "
        f"= {1.0 / fps:.4g} s{unit}. Check frames.csv's timestamp_s units and camera.yaml's fps: "
        "GPS and OBD are matched to the frames by these times."
    )


def check_static(gps: GpsTrack, frames: list[Frame], warnings: list[str]) -> bool:
    """Warn (and return True) when every GPS fix over the frames stays within the noise of one
    position (the log's stated σ, else HDOP-derived) and the fixes do not progress, while the
    frames span at least ``STATIC_MIN_S``."""
    t0, t1 = frames[0].timestamp_s, frames[-1].timestamp_s
    inside = (gps.timestamp_s >= t0) & (gps.timestamp_s <= t1)
    if t1 - t0 < STATIC_MIN_S or inside.sum() < 3:
        return False
    lat, lon = gps.lat_deg[inside], gps.lon_deg[inside]
    n = len(lat)
    d = _dist_m(np.full(n, np.median(lat)), np.full(n, np.median(lon)), lat, lon)
    stated = gps.sigma_m[inside]
    stated = stated[np.isfinite(stated) & (stated > 0)]
    # the receiver's own σ where it states one (an RTK log's cm, not HDOP's metres)
    sigma = float(np.median(stated)) if stated.size else fix_sigma_m(gps.hdop[inside])
    radius = STATIC_K * sigma
    if float(d.max()) > radius:
        return False
    # A slow vehicle stays within HDOP's metres for seconds, but its fixes progress: the first
    # and last thirds' medians lie apart by more than one fix's σ (a still receiver's wander
    # over seconds is well below it).
    m = max(n // 3, 1)
    net = _dist_m(np.median(lat[:m]), np.median(lon[:m]), np.median(lat[-m:]), np.median(lon[-m:]))
    if float(net[0]) > sigma:
        return False
    source = "stated by the log" if stated.size else "from HDOP"
    warnings.append(
        f"{gps.source}: the GPS position stays within {d.max():.1f} m (the fixes' noise is "
        f"{radius:.1f} m, {STATIC_K:.0f} σ {source}) over {t1 - t0:.1f} s of frames "
        f"({len(frames)} frames, {n} fixes): a static receiver (frozen, or not on the vehicle) or "
        f"a vehicle that never moved. Check the GPS log; the map scale cannot come from it."
    )
    return True


def _path_m(gps: GpsTrack, tg: np.ndarray, i: int, j: int, step_s: float) -> float:
    """Length (m) of the GPS path from fix i to fix j through fixes ``step_s`` apart."""
    keep = [i]
    for k in range(i + 1, j):
        if tg[k] - tg[keep[-1]] >= step_s and tg[j] - tg[k] >= 0.5 * step_s:
            keep.append(k)
    keep.append(j)
    ks = np.array(keep)
    lat, lon = gps.lat_deg, gps.lon_deg
    return float(np.sum(_dist_m(lat[ks[:-1]], lon[ks[:-1]], lat[ks[1:]], lon[ks[1:]])))


def check_obd_vs_gps(path: Path, obd: ObdLog, gps: GpsTrack, warnings: list[str]) -> ObdLog | None:
    """Compare OBD speed with the GPS ground speed over their common time span.

    Ground speed: over windows ``OBD_WINDOW_S`` long (the whole overlap when it is shorter),
    both the chord and the path (geodesic steps between fixes ``OBD_STEP_S`` apart), against
    the OBD distance integrated over the same times (the log agrees when either does); the
    ratio is the median
    over the windows long enough to beat the GPS noise (5 σ). A ratio of 3.6 (±15 %) means km/h
    typed as m/s: the log is divided by 3.6 (the unit slip is unambiguous and the conversion
    exact, and OBD is smoother than GPS-derived speed). Any other ratio beyond ±25 %: the log is
    ignored (None). Too little overlap or motion: no check, the log unchanged."""
    to, vo = np.asarray(obd.timestamp_s, float), np.asarray(obd.speed_mps, float)
    tg = np.asarray(gps.timestamp_s, float)
    idx = np.flatnonzero((tg >= to[0]) & (tg <= to[-1]))
    if len(to) < 2 or len(idx) < 2:
        return obd
    with np.errstate(over="ignore", invalid="ignore"):  # absurd times (the fuzz test's 1e308)
        s_obd = np.r_[0.0, np.cumsum(0.5 * (vo[1:] + vo[:-1]) * np.diff(to))]
    ends: list[tuple[int, int]] = []
    i = int(idx[0])
    for j in idx[1:]:
        if tg[j] - tg[i] >= OBD_WINDOW_S:
            ends.append((i, int(j)))
            i = int(j)
    if not ends:
        ends = [(int(idx[0]), int(idx[-1]))]
    a = np.array([e[0] for e in ends])
    b = np.array([e[1] for e in ends])
    chord = _dist_m(gps.lat_deg[a], gps.lon_deg[a], gps.lat_deg[b], gps.lon_deg[b])
    walked = np.array([_path_m(gps, tg, i, j, OBD_STEP_S) for i, j in ends])
    d_obd = np.interp(tg[b], to, s_obd) - np.interp(tg[a], to, s_obd)
    sigma = fix_sigma_m(gps.hdop)
    floor = 5.0 * math.sqrt(2.0) * sigma
    use = (chord >= floor) | (d_obd >= floor)
    if not use.any():
        log.info("%s: too little motion over the GPS overlap to compare OBD with GPS speed", path)
        return obd
    # Two GPS distances, each wrong one way: the chord reads a turn short (a 40 m U-turn:
    # 2.3x), the path through 1 s steps adds the fixes' noise to every step (σ 2 m at 2 m/s:
    # 2x long). The OBD log agrees with GPS when either says so, and holds km/h when either
    # reads 3.6; the one nearer to 1 is quoted.
    ratios = [float(np.median(d_obd[use] / np.maximum(d[use], sigma))) for d in (chord, walked)]
    pick = int(np.argmin([abs(math.log(max(r, 1e-9))) for r in ratios]))
    ratio, d_gps = ratios[pick], (chord, walked)[pick]
    span = float(np.sum(tg[b[use]] - tg[a[use]]))
    v_obd, v_gps = float(d_obd[use].sum()) / span, float(d_gps[use].sum()) / span
    figures = f"OBD {v_obd:.2f} m/s vs GPS {v_gps:.2f} m/s over {span:.1f} s, ratio {ratio:.2f}"
    if abs(ratio - 1.0) <= OBD_TOL:
        return obd
    kmh = [k for k, r in enumerate(ratios) if abs(r / KMH_PER_MPS - 1.0) <= KMH_TOL]
    if kmh:
        ratio, v_gps = ratios[kmh[0]], float((chord, walked)[kmh[0]][use].sum()) / span
        figures = f"OBD {v_obd:.2f} m/s vs GPS {v_gps:.2f} m/s over {span:.1f} s, ratio {ratio:.2f}"
        warnings.append(
            f"{path}: OBD speed is {KMH_PER_MPS}x the GPS ground speed ({figures}): speed_mps "
            f"holds km/h. The log was converted (divided by 3.6) and is used; write m/s in "
            f"obd.csv to silence this."
        )
        return ObdLog(timestamp_s=obd.timestamp_s, speed_mps=vo / KMH_PER_MPS)
    if abs(ratio - 1.0) > OBD_TOL:
        warnings.append(
            f"{path}: OBD speed disagrees with the GPS ground speed by {100 * (ratio - 1):+.0f} % "
            f"({figures}; tolerance ±{100 * OBD_TOL:.0f} %), so the OBD log is ignored. Check "
            f"its units (m/s) and clock (same as frames.csv)."
        )
        return None
    return obd
