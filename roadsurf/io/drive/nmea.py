"""gps.nmea: $xxRMC and $xxGGA sentences (checksummed), merged into one fix per epoch."""

from __future__ import annotations

import calendar
import logging
import math
import re
from pathlib import Path
from typing import Any

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive.gps import gps_from_lists, valid_latlon
from roadsurf.io.drive.types import GpsTrack, Skipped

log = logging.getLogger(__name__)

# Hand-written on purpose for now; an NMEA library (pynmea2) is a later issue.
_NMEA_RE = re.compile(r"^\$([A-Z]{2})(RMC|GGA),(.*)\*([0-9A-Fa-f]{2})\s*$")


def _nmea_deg(value: str, hemi: str) -> float:
    """ddmm.mmmm / dddmm.mmmm + N/S/E/W -> signed degrees."""
    if not value or hemi not in ("N", "S", "E", "W"):
        return math.nan
    v = float(value)
    deg = math.floor(v / 100.0)
    d = deg + (v - deg * 100.0) / 60.0
    return -d if hemi in ("S", "W") else d


def _nmea_tod(hhmmss: str) -> float:
    """hhmmss.ss -> seconds of the day."""
    if len(hhmmss) < 6:
        raise ValueError("bad time")
    return int(hhmmss[0:2]) * 3600 + int(hhmmss[2:4]) * 60 + float(hhmmss[4:])


def load_gps_nmea(path: Path, skipped: list[Skipped], warnings: list[str]) -> GpsTrack | None:
    """$xxRMC gives date/time/position; $xxGGA gives time/position/HDOP/altitude. Sentences of
    the same second are merged into one fix. Times become UNIX seconds (UTC) using the RMC date."""
    fixes: dict[float, dict[str, Any]] = {}  # key: seconds of day (+ day offset)
    n_bad = n_sent = 0
    day0: float | None = None  # UNIX seconds at 00:00 UTC of the current date
    first_day0: float | None = None
    last_tod: float | None = None
    pending_gga: list[tuple[int, float, dict[str, Any]]] = []  # GGA seen before any RMC date
    with open(path, encoding="ascii", errors="replace") as f:
        for line_no, raw in enumerate(f, start=1):
            s = raw.strip()
            if not s.startswith("$"):
                continue
            m = _NMEA_RE.match(s)
            if m is None:
                if s[3:6] in ("RMC", "GGA"):
                    n_sent += 1
                    n_bad += 1
                    skipped.append(Skipped(path.name, line_no, "malformed NMEA sentence"))
                continue  # other sentence types are ignored
            n_sent += 1
            body = s[1 : s.rindex("*")]
            chk = 0
            for ch in body:
                chk ^= ord(ch)
            if chk != int(m.group(4), 16):
                n_bad += 1
                skipped.append(Skipped(path.name, line_no, "NMEA checksum mismatch"))
                continue
            kind, fields = m.group(2), m.group(3).split(",")
            try:
                if kind == "RMC":
                    # time,status,lat,N,lon,E,speed_kn,course,date(ddmmyy),...
                    if len(fields) < 9:
                        raise ValueError("too few fields")
                    tod = _nmea_tod(fields[0])
                    if fields[1] != "A":
                        raise ValueError("status V (no fix)")
                    lat, lon = _nmea_deg(fields[2], fields[3]), _nmea_deg(fields[4], fields[5])
                    d = fields[8]
                    if len(d) != 6:
                        raise ValueError("bad date")
                    yy = int(d[4:6])
                    day0 = float(
                        calendar.timegm(
                            (2000 + yy if yy < 80 else 1900 + yy, int(d[2:4]), int(d[0:2]), 0, 0, 0)
                        )
                    )
                    if first_day0 is None:
                        first_day0 = day0
                    rec: dict[str, Any] = {"lat": lat, "lon": lon}
                else:
                    # time,lat,N,lon,E,quality,nsat,hdop,alt,M,...
                    if len(fields) < 9:
                        raise ValueError("too few fields")
                    tod = _nmea_tod(fields[0])
                    if fields[5] in ("", "0"):
                        raise ValueError("fix quality 0 (no fix)")
                    lat, lon = _nmea_deg(fields[1], fields[2]), _nmea_deg(fields[3], fields[4])
                    rec = {
                        "lat": lat,
                        "lon": lon,
                        "hdop": float(fields[7]) if fields[7] else math.nan,
                        "alt": float(fields[8]) if fields[8] else math.nan,
                    }
            except ValueError as e:
                n_bad += 1
                skipped.append(Skipped(path.name, line_no, f"NMEA {kind} dropped: {e}"))
                continue
            why = valid_latlon(rec["lat"], rec["lon"])
            if why is not None:
                n_bad += 1
                skipped.append(Skipped(path.name, line_no, f"NMEA {kind} dropped: {why}"))
                continue
            if day0 is None:
                pending_gga.append((line_no, tod, rec))
                continue
            if last_tod is not None and tod < last_tod - 43200 and kind == "GGA":
                day0 += 86400.0  # midnight rollover between RMC sentences
            last_tod = tod
            t = round(day0 + tod, 3)
            fx = fixes.setdefault(t, {"line": line_no})
            for k2, v2 in rec.items():
                if k2 in ("lat", "lon") and k2 in fx:
                    continue  # first sentence of the epoch wins for position
                fx[k2] = v2
    if pending_gga:
        if first_day0 is None:
            raise DriveFormatError(
                f"{path}: NMEA log has $GPGGA but no valid $GPRMC sentence, so the date is "
                f"unknown and GPS times cannot be matched to frames.csv. Log RMC sentences too."
            )
        # GGA sentences before the first RMC: use the first RMC's date.
        d0 = first_day0
        for line_no, tod, rec in pending_gga:
            fx = fixes.setdefault(round(d0 + tod, 3), {"line": line_no})
            for k2, v2 in rec.items():
                fx.setdefault(k2, v2)
    if n_sent == 0:
        raise DriveFormatError(
            f"{path}: no $GPRMC/$GPGGA sentences found. Record RMC and GGA sentences."
        )
    good = [
        (
            fx["line"],
            t,
            fx["lat"],
            fx["lon"],
            fx.get("alt", math.nan),
            fx.get("hdop", math.nan),
        )
        for t, fx in sorted(fixes.items())
    ]
    if n_bad:
        log.info("%s: %d of %d RMC/GGA sentences skipped", path, n_bad, n_sent)
    return gps_from_lists(path, good, skipped, n_bad, n_sent, warnings)
