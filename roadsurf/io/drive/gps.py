"""GPS logs: fix validation and track assembly shared by the CSV, GPX and NMEA readers, the
gps.csv reader, and the check that the track overlaps the frame times."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive.checks import reject_jumps
from roadsurf.io.drive.csvrows import check_increasing, csv_float, csv_rows
from roadsurf.io.drive.types import (
    ALT_ELLIPSOIDAL,
    ALT_NONE,
    NO_GEOREF,
    Frame,
    GpsTrack,
    Skipped,
    disjoint_text,
    log_overlap,
)


def valid_latlon(lat: float, lon: float) -> str | None:
    if not (math.isfinite(lat) and math.isfinite(lon)):
        return "lat/lon is NaN or missing"
    if abs(lat) > 90 or abs(lon) > 180:
        return f"lat/lon ({lat}, {lon}) out of range"
    if lat == 0.0 and lon == 0.0:
        return "lat/lon is (0, 0), a receiver's no-fix placeholder"
    return None


Row = (
    tuple[int | None, float, float, float, float, float]
    | tuple[int | None, float, float, float, float, float, float, float]
)


def gps_from_lists(
    path: Path,
    rows: Sequence[Row],
    skipped: list[Skipped],
    n_bad: int,
    n_total: int,
    warnings: list[str],
    alt_datum: str = ALT_ELLIPSOIDAL,
) -> GpsTrack | None:
    """rows: (line, t, lat, lon, alt, hdop[, sigma_m, quality]) of fixes that passed validation
    (sigma_m: the receiver's stated horizontal σ, NaN if none; quality: the GGA fix quality, 0 if
    none); ``alt_datum``: the vertical datum of their altitudes. Fixes that jump impossibly far
    are rejected here."""
    rows = [r if len(r) == 8 else (*r, math.nan, 0.0) for r in rows]
    # A row repeated verbatim (same time and position; some loggers write a fix twice) carries
    # no information: drop it. Any other non-increasing time is an error below.
    dedup: list[Row] = []
    n_dup = 0
    for r in rows:
        if dedup and r[1] == dedup[-1][1] and r[2:4] == dedup[-1][2:4]:
            where = f"line {r[0]}" if r[0] is not None else f"time {r[1]}"
            skipped.append(Skipped(path.name, r[0], f"duplicate GPS fix ({where}) dropped"))
            n_dup += 1
            continue
        dedup.append(r)
    rows = dedup
    if n_bad:
        warnings.append(
            f"{path}: dropped {n_bad} of {n_total} GPS record(s) (bad or out-of-range values; "
            f"see report skipped list)."
        )
    if n_dup:  # harmless, but a logger writing each fix twice is worth knowing of
        warnings.append(
            f"{path}: {n_dup} of {n_total} GPS record(s) repeat the previous one verbatim (same "
            "time and position) and were dropped."
        )
    if not rows:
        warnings.append(
            f"{path}: no valid GPS fix (all {n_total} record(s) rejected, see report skipped "
            f"list); {NO_GEOREF}. Fix the GPS log to get a georeferenced map."
        )
        return None
    arr = np.array([r[1:] for r in rows], dtype=float)
    lines = [r[0] or 0 for r in rows]
    if any(r[0] is None for r in rows):
        bad = np.flatnonzero(np.diff(arr[:, 0]) <= 0)
        if bad.size:
            i = int(bad[0])
            raise DriveFormatError(
                f"{path}: GPS fix #{i + 2} (time {float(arr[i + 1, 0])!r} s) is not after fix #{i + 1} "
                f"({float(arr[i, 0])!r} s). GPS times must strictly increase; fix the log."
            )
    else:
        check_increasing(arr[:, 0], lines, path, "GPS")
    keep = reject_jumps(
        path, arr[:, 0], arr[:, 1], arr[:, 2], [r[0] for r in rows], skipped, warnings
    )
    arr = arr[keep]
    datum = alt_datum if np.isfinite(arr[:, 3]).any() else ALT_NONE
    return GpsTrack(
        timestamp_s=arr[:, 0],
        lat_deg=arr[:, 1],
        lon_deg=arr[:, 2],
        alt_m=arr[:, 3],
        hdop=arr[:, 4],
        sigma_m=arr[:, 5],
        quality=arr[:, 6].astype(np.int64),
        source=path.name,
        alt_datum=datum,
    )


def load_gps_csv(path: Path, skipped: list[Skipped], warnings: list[str]) -> GpsTrack | None:
    _, rows = csv_rows(
        path, ("timestamp_s", "lat", "lon"), ("alt_m", "hdop", "sigma_m", "fix_quality")
    )
    good: list[Row] = []
    bad_acc: list[int | None] = []  # lines whose sigma_m / fix_quality is not a valid value
    n_total = n_bad = 0
    for line, row in rows:
        n_total += 1
        try:
            t = float(row["timestamp_s"])
        except ValueError:
            t = math.nan
        if not math.isfinite(t):
            n_bad += 1
            skipped.append(Skipped(path.name, line, "GPS row without a numeric timestamp_s"))
            continue
        try:
            lat, lon = csv_float(row["lat"]), csv_float(row["lon"])
        except ValueError:
            lat = lon = math.nan
        why = valid_latlon(lat, lon)
        if why is not None:
            n_bad += 1
            skipped.append(Skipped(path.name, line, f"GPS row dropped: {why}"))
            continue
        try:
            alt = csv_float(row.get("alt_m", ""))
        except ValueError:
            alt = math.nan
        try:
            hdop = csv_float(row.get("hdop", ""))
        except ValueError:
            hdop = math.nan
        if math.isfinite(hdop) and hdop <= 0:
            hdop = math.nan
        sigma, quality = _accuracy(path, line, row, bad_acc)
        good.append((line, t, lat, lon, alt, hdop, sigma, quality))
    if bad_acc:
        first = ", ".join(str(n) for n in bad_acc[:5])
        warnings.append(
            f"{path}: sigma_m (the receiver's horizontal σ, m, > 0 and <= {MAX_SIGMA_M:g}) or "
            f"fix_quality (the GGA fix quality, an integer 0-9) is not valid on {len(bad_acc)} "
            f"row(s) (line {first}{', ...' if len(bad_acc) > 5 else ''}): taken as not stated"
        )
    return gps_from_lists(path, good, skipped, n_bad, n_total, warnings)


def check_overlap(gps: GpsTrack, frames: list[Frame], warnings: list[str]) -> GpsTrack | None:
    # A fix slightly outside the frame span still helps: one GPS interval of slack.
    slack, covered = log_overlap(gps.timestamp_s, frames)
    if covered is None:
        warnings.append(
            f"{gps.source}: GPS {disjoint_text(gps.timestamp_s, frames)}, so the GPS is ignored: "
            f"{NO_GEOREF}. Write frames.csv times in the same clock as the GPS (UNIX seconds, "
            f"UTC, for GPX/NMEA logs)."
        )
        return None
    if covered < 0.9:
        warnings.append(
            f"{gps.source}: GPS covers only {100 * max(covered, 0):.0f}% of the frame time span; "
            f"frames outside it are placed by visual chaining."
        )
    sparse = few_fixes_inside(gps, frames)
    if sparse:
        warnings.append(f"{gps.source}: {sparse}")
    outage = gps_outages(gps, frames, slack)
    if outage:
        warnings.append(
            f"{gps.source}: no fix for {outage} (the log's interval is {slack:.2g} s); the "
            "frames there are placed by visual chaining alone, which drifts with its length"
        )
    return gps


# a drive with fewer fixes than this within its frames' span, whose nearest fixes beyond its
# ends lie further than EXTRAPOLATE_WARN_S away, is placed by extrapolating the visual
# trajectory to them: ½·a·Δt² on a curve (a 0.2 Hz log around a 2.3 s drive: 131 mm off)
MIN_FIXES_INSIDE = 2
EXTRAPOLATE_WARN_S = 1.0


def few_fixes_inside(gps: GpsTrack, frames: list[Frame]) -> str:
    """What to say when the drive's position rests on fixes well beyond its ends (text), or ""."""
    ts = np.asarray(gps.timestamp_s, float)
    t0, t1 = frames[0].timestamp_s, frames[-1].timestamp_s
    n_in = int(np.sum((ts >= t0) & (ts <= t1)))
    before, after = ts[ts < t0], ts[ts > t1]
    reach = max(t0 - before[-1] if before.size else 0.0, after[0] - t1 if after.size else 0.0)
    if n_in >= MIN_FIXES_INSIDE or reach <= EXTRAPOLATE_WARN_S:
        return ""
    return (
        f"only {n_in} fix(es) fall within the frames' {t1 - t0:.1f} s, and the nearest others lie "
        f"up to {reach:.1f} s beyond its ends: the drive's position and heading come from "
        "extrapolating the visual trajectory to them, centimetres to decimetres off on a curve. "
        "A log of 1 Hz or more (or a longer drive) avoids it."
    )


# an outage is a gap between fixes longer than this many of the log's median intervals, and at
# least OUTAGE_MIN_S: a 1 Hz receiver losing two fixes is not news, a tunnel or a dead logger is
OUTAGE_INTERVALS = 3.0
OUTAGE_MIN_S = 2.0


def gps_outages(gps: GpsTrack, frames: list[Frame], interval_s: float) -> str:
    """The GPS outages within the frame time span, as text (times and frames; at most three,
    then a count), or "" when there is none."""
    ts = np.asarray(gps.timestamp_s, float)
    tf = np.array([f.timestamp_s for f in frames], float)
    limit = max(OUTAGE_INTERVALS * interval_s, OUTAGE_MIN_S)
    parts = []
    for k in np.flatnonzero(np.diff(ts) > limit):
        inside = (tf > ts[k]) & (tf < ts[k + 1])
        if inside.any():
            i0, i1 = np.flatnonzero(inside)[[0, -1]]
            parts.append(
                f"{ts[k + 1] - ts[k]:.1f} s between {ts[k]:.2f} and {ts[k + 1]:.2f} s "
                f"({inside.sum()} frames, {frames[i0].filename} to {frames[i1].filename})"
            )
    if len(parts) > 3:
        return "; ".join(parts[:3]) + f"; and {len(parts) - 3} more outages"
    return "; ".join(parts)


MAX_SIGMA_M = 1000.0  # a stated σ above this is a unit mistake (mm typed as m?)


def _accuracy(
    path: Path, line: int | None, row: dict[str, str], bad: list[int | None]
) -> tuple[float, float]:
    """(stated σ (m), NaN if none; fix quality, 0 if none) of one gps.csv row. A value that is
    not a number or out of range counts as not stated, its line appended to ``bad`` (one
    warning names them): the columns are optional and unused by default, a log that loaded
    before still loads."""
    out = [math.nan, 0.0]
    for k, key in enumerate(("sigma_m", "fix_quality")):
        text = (row.get(key) or "").strip()
        if not text:
            continue
        try:
            v = csv_float(text)
        except ValueError:
            v = math.nan
        if k == 0:
            ok = math.isfinite(v) and 0 < v <= MAX_SIGMA_M
        else:
            ok = math.isfinite(v) and v == int(v) and 0 <= v <= 9
        if ok:
            out[k] = v
        elif not bad or bad[-1] != line:
            bad.append(line)
    return out[0], out[1]
