"""gps.nmea: $xxRMC and $xxGGA sentences (checksummed), merged into one fix per epoch.

pynmea2 parses each sentence (checksum, fields, time, date). Finding the sentences is ours: a
receiver log may interleave binary messages (u-blox UBX) with NMEA on the same line, so every
``$`` starts a candidate that ends at the first non-printable byte, and everything outside the
sentences is counted as skipped garbage and reported in one warning.
"""

from __future__ import annotations

import calendar
import datetime as dt
import logging
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pynmea2

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive.gps import gps_from_lists, valid_latlon
from roadsurf.io.drive.textfile import read_bytes
from roadsurf.io.drive.types import ALT_ELLIPSOIDAL, ALT_MSL, ALT_NONE, GpsTrack, Skipped

log = logging.getLogger(__name__)

_CANDIDATE = re.compile(rb"\$[\x20-\x23\x25-\x7e]*")  # '$' + printable ASCII except '$'
_CHECKSUMMED = re.compile(rb"\$[^*]*\*[0-9A-Fa-f]{2}")  # a sentence up to its checksum
# A sentence of another type (GSV, VTG, $PUBX, ...): ignored, and not counted as garbage.
_OTHER = re.compile(r"^\$[A-Z][A-Z0-9]{3,5},[\x20-\x7e]*$")


def _nmea_deg(value: str, hemi: str) -> float:
    """ddmm.mmmm / dddmm.mmmm + N/S/E/W -> signed degrees.

    Kept hand-written: pynmea2's ``latitude`` returns 0.0 for an empty field or hemisphere (a
    missing position would pass as a fix), and this arithmetic gives the same floats as earlier
    releases (pynmea2 splits the minutes as text, which differs in the last bit)."""
    if not value or hemi not in ("N", "S", "E", "W"):
        return math.nan
    v = float(value)
    if not math.isfinite(v):
        return math.nan
    deg = math.floor(v / 100.0)
    d = deg + (v - deg * 100.0) / 60.0
    return -d if hemi in ("S", "W") else d


def _num(v: object) -> float:
    """A pynmea2 field as a float: empty -> NaN; text raises ValueError."""
    if v is None or v == "":
        return math.nan
    return float(v)  # type: ignore[arg-type]  # str, or a float pynmea2 converted already


def _tod(msg: Any) -> float:
    """Seconds of the day of the sentence's hhmmss.ss time."""
    t = msg.timestamp  # pynmea2 returns the raw text when it cannot convert it
    if not isinstance(t, dt.time):
        raise ValueError("bad time")
    return t.hour * 3600 + t.minute * 60 + t.second + t.microsecond / 1e6


class _Scan:
    """Sentences of a raw NMEA log, with the count of bytes that belong to none."""

    def __init__(self) -> None:
        self.garbage_bytes = 0
        self.garbage_lines: list[int] = []
        self.resynced = 0  # sentences found after garbage on the same line

    def sentences(self, data: bytes) -> list[tuple[int, str, bool]]:
        """(line number, sentence text, whether it is the whole line) of every RMC/GGA-looking
        or well-formed sentence."""
        out: list[tuple[int, str, bool]] = []
        for line_no, line in enumerate(data.split(b"\n"), start=1):
            pos = 0
            junk = 0
            for m in _CANDIDATE.finditer(line):
                cand = m.group()
                c = _CHECKSUMMED.match(cand)
                sent = c.group() if c else cand.rstrip()
                junk += len(line[pos : m.start()].strip())
                pos = m.end()
                text = sent.decode("ascii")
                if text[3:6] not in ("RMC", "GGA") and not self._other_ok(text):
                    junk += len(sent)  # a '$' inside binary data, or a broken sentence
                    continue
                if junk:
                    self.resynced += 1
                junk += len(cand[len(sent) :].strip())  # bytes after the checksum
                # a whole line: no binary cut it (a sentence without a checksum may be read)
                out.append((line_no, text, line.strip() == sent))
            junk += len(line[pos:].strip())
            if junk:
                self.garbage_bytes += junk
                self.garbage_lines.append(line_no)
        return out

    @staticmethod
    def _other_ok(text: str) -> bool:
        if not _OTHER.match(text):
            return False
        star = text.rfind("*")
        if star < 0 or len(text) - star != 3:
            return True  # no checksum: a plain sentence of a type we do not read
        try:
            return pynmea2.NMEASentence.checksum(text[1:star]) == int(text[star + 1 :], 16)
        except ValueError:
            return False


def _record(msg: Any, kind: str) -> tuple[float, dict[str, Any], dt.date | None]:
    """(seconds of day, fields, RMC date) of one RMC/GGA sentence; ValueError when unusable."""
    f = msg.data
    if len(f) < 9:
        raise ValueError("too few fields")
    tod = _tod(msg)
    if kind == "RMC":
        # time,status,lat,N,lon,E,speed_kn,course,date(ddmmyy),...
        if msg.status != "A":
            raise ValueError("status V (no fix)")
        lat, lon = _nmea_deg(msg.lat, msg.lat_dir), _nmea_deg(msg.lon, msg.lon_dir)
        date = msg.datestamp
        if len(f[8]) != 6 or not isinstance(date, dt.date):
            raise ValueError("bad date")
        return tod, {"lat": lat, "lon": lon}, date
    # time,lat,N,lon,E,quality,nsat,hdop,alt(MSL),M,geoid separation,M,...
    if f[5] in ("", "0"):
        raise ValueError("fix quality 0 (no fix)")
    lat, lon = _nmea_deg(msg.lat, msg.lat_dir), _nmea_deg(msg.lon, msg.lon_dir)
    rec = {
        "lat": lat,
        "lon": lon,
        "hdop": _num(msg.horizontal_dil),
        "alt": _num(msg.altitude),
        "sep": _num(msg.geo_sep),
        "quality": float(int(f[5])) if f[5].isdigit() else 0.0,
    }
    for k in ("hdop", "alt", "sep"):
        if not math.isfinite(rec[k]):
            rec[k] = math.nan
    return tod, rec, None


def load_gps_nmea(path: Path, skipped: list[Skipped], warnings: list[str]) -> GpsTrack | None:
    """$xxRMC gives date/time/position; $xxGGA gives time/position/HDOP/altitude. Sentences of
    the same second are merged into one fix. Times become UNIX seconds (UTC) using the RMC date.
    Heights are ellipsoidal: GGA altitude (mean sea level) + geoid separation."""
    fixes: dict[float, dict[str, Any]] = {}  # key: seconds of day (+ day offset)
    n_bad = n_sent = n_unchecked = 0
    day0: float | None = None  # UNIX seconds at 00:00 UTC of the current date
    first_day0: float | None = None
    first_tod = 0.0  # the first dated sentence's seconds of day
    last_tod: float | None = None
    pending_gga: list[tuple[int, float, dict[str, Any]]] = []  # GGA seen before any RMC date
    gst: dict[float, float] = {}  # seconds of day -> the GST's horizontal σ per axis (m)
    scan = _Scan()
    for line_no, s, whole in scan.sentences(read_bytes(path)):
        kind = s[3:6]
        if kind == "GST":
            _read_gst(s, gst, skipped, path.name, line_no)
            continue
        if kind not in ("RMC", "GGA"):
            continue  # other sentence types are ignored
        n_sent += 1
        try:
            msg = pynmea2.parse(s, check=True)
        except pynmea2.ChecksumError as e:
            missing = "missing" in str(e)
            if not missing or not whole:
                n_bad += 1
                why = "malformed NMEA sentence" if missing else "NMEA checksum mismatch"
                skipped.append(Skipped(path.name, line_no, why))
                continue
            # no checksum at all (a logger that strips it): read, but say it was unchecked
            try:
                msg = pynmea2.parse(s, check=False)
            except pynmea2.ParseError:
                n_bad += 1
                skipped.append(Skipped(path.name, line_no, "malformed NMEA sentence"))
                continue
            n_unchecked += 1
        except pynmea2.ParseError:
            n_bad += 1
            skipped.append(Skipped(path.name, line_no, "malformed NMEA sentence"))
            continue
        if not isinstance(msg, (pynmea2.RMC, pynmea2.GGA)):
            n_sent -= 1  # e.g. a proprietary $PxRMC sentence: not ours
            continue
        try:
            tod, rec, date = _record(msg, kind)
        except ValueError as e:
            n_bad += 1
            skipped.append(Skipped(path.name, line_no, f"NMEA {kind} dropped: {e}"))
            continue
        bad_ll = valid_latlon(rec["lat"], rec["lon"])
        if bad_ll is not None:
            n_bad += 1
            skipped.append(Skipped(path.name, line_no, f"NMEA {kind} dropped: {bad_ll}"))
            continue
        if date is not None:
            day0 = float(calendar.timegm(date.timetuple()))
            if first_day0 is None:
                first_day0, first_tod = day0, tod
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
    if scan.garbage_bytes:
        first = ", ".join(str(n) for n in scan.garbage_lines[:5])
        warnings.append(
            f"{path}: skipped {scan.garbage_bytes} byte(s) of binary or garbled data (not NMEA "
            f"sentences) on {len(scan.garbage_lines)} line(s) (line {first}"
            f"{', ...' if len(scan.garbage_lines) > 5 else ''}); {scan.resynced} sentence(s) "
            f"following such data on the same line were read. Log NMEA only (no UBX) to avoid it."
        )
    if pending_gga:
        if first_day0 is None:
            raise DriveFormatError(
                f"{path}: NMEA log has $GPGGA but no valid $GPRMC sentence, so the date is "
                f"unknown and GPS times cannot be matched to frames.csv. Log RMC sentences too."
            )
        # GGA sentences before the first RMC: the first RMC's date, or the day before for a
        # time of day half a day after the RMC's (23:59:58 logged before an RMC at 00:00:01)
        for line_no, tod, rec in pending_gga:
            d0 = first_day0 - (86400.0 if tod - first_tod > 43200.0 else 0.0)
            fx = fixes.setdefault(round(d0 + tod, 3), {"line": line_no})
            for k2, v2 in rec.items():
                fx.setdefault(k2, v2)
    if n_sent == 0:
        raise DriveFormatError(
            f"{path}: no $GPRMC/$GPGGA sentences found. Record RMC and GGA sentences."
        )
    order = sorted(fixes.items())
    alt, datum = _ellipsoidal(path, [fx for _, fx in order], warnings)
    good = [
        (
            fx["line"], t, fx["lat"], fx["lon"], a, fx.get("hdop", math.nan),
            gst.get(round(t % 86400.0, 3), math.nan), fx.get("quality", 0.0),
        )
        for (t, fx), a in zip(order, alt, strict=True)
    ]  # fmt: skip
    if gst and not any(math.isfinite(g[6]) for g in good):
        warnings.append(
            f"{path}: {len(gst)} GST sentence(s) (the receiver's position σ) match no RMC/GGA "
            "fix time; the fixes carry no stated σ"
        )
    if n_bad:
        log.info("%s: %d of %d RMC/GGA sentences skipped", path, n_bad, n_sent)
    if n_unchecked:
        warnings.append(
            f"{path}: {n_unchecked} of {n_sent} RMC/GGA sentences carry no checksum (*hh) and "
            "were read unchecked: a corrupted digit would pass; log with checksums if the "
            "receiver allows it"
        )
    return gps_from_lists(path, good, skipped, n_bad, n_sent, warnings, alt_datum=datum)


def _read_gst(
    s: str, gst: dict[float, float], skipped: list[Skipped], name: str, line_no: int
) -> None:
    """One $xxGST sentence into ``gst`` (seconds of day -> horizontal σ per axis, m: the RMS of
    its latitude and longitude σ, fields 6 and 7). A GST that does not parse, or states no
    positive σ, is skipped with its line."""
    try:
        try:
            msg = pynmea2.parse(s, check=True)
        except pynmea2.ChecksumError as e:
            if "missing" not in str(e):
                raise
            msg = pynmea2.parse(s, check=False)  # no checksum at all: read, as RMC/GGA are
        tod = _tod(msg)
        sl, so = float(msg.std_dev_latitude), float(msg.std_dev_longitude)
    except (pynmea2.ParseError, pynmea2.ChecksumError, ValueError, TypeError, AttributeError):
        skipped.append(Skipped(name, line_no, "NMEA GST dropped: malformed"))
        return
    if not (math.isfinite(sl) and math.isfinite(so) and sl > 0 and so > 0):
        skipped.append(Skipped(name, line_no, "NMEA GST dropped: no positive position σ"))
        return
    gst[round(tod, 3)] = math.sqrt(0.5 * (sl * sl + so * so))


def _ellipsoidal(
    path: Path, fixes: list[dict[str, Any]], warnings: list[str]
) -> tuple[list[float], str]:
    """Heights of the fixes and their datum: GGA altitude (MSL) + geoid separation (field 11)."""
    alt = np.array([fx.get("alt", math.nan) for fx in fixes], dtype=float)
    sep = np.array([fx.get("sep", math.nan) for fx in fixes], dtype=float)
    has_alt = np.isfinite(alt)
    if not has_alt.any():
        return alt.tolist(), ALT_NONE
    known = has_alt & np.isfinite(sep)
    if not known.any():
        warnings.append(
            f"{path}: GGA sentences give no geoid separation (field 11), so heights are above "
            f"mean sea level, not WGS84 ellipsoidal heights (they can differ by tens of metres). "
            f"Configure the receiver to report the geoid separation for ellipsoidal heights."
        )
        return alt.tolist(), ALT_MSL
    if not known[has_alt].all():
        # The geoid changes by centimetres over a drive: the others' separation serves.
        fill = float(np.median(sep[known]))
        n_fill = int((has_alt & ~known).sum())
        warnings.append(
            f"{path}: {n_fill} GGA fix(es) lack the geoid separation; used {fill:.2f} m, the "
            f"median of the other fixes, for their ellipsoidal heights."
        )
        sep = np.where(known, sep, fill)
    return (alt + sep).tolist(), ALT_ELLIPSOIDAL
