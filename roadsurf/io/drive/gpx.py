"""gps.gpx: track points (<trkpt> with lat/lon, <time>, optional <ele> and <hdop>)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from datetime import UTC, datetime
from pathlib import Path

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive.gps import gps_from_lists, valid_latlon
from roadsurf.io.drive.types import GpsTrack, Skipped

# Hand-written on purpose for now; a GPX library (gpxpy) is a later issue.


def _parse_iso_time(s: str) -> float:
    """ISO 8601 time -> UNIX seconds (UTC when no offset is given)."""
    s = s.strip()
    if s.endswith(("Z", "z")):
        s = s[:-1] + "+00:00"
    dt = datetime.fromisoformat(s)
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return dt.timestamp()


def _num(d: dict[str, str], key: str) -> float:
    try:
        return float(d[key]) if d.get(key) else math.nan
    except ValueError:
        return math.nan


def load_gps_gpx(path: Path, skipped: list[Skipped], warnings: list[str]) -> GpsTrack | None:
    try:
        tree = ET.parse(path)
    except ET.ParseError as e:
        line = e.position[0] if getattr(e, "position", None) else None
        raise DriveFormatError(
            f"{path}:{line}: not valid XML ({e}). Fix or re-export the GPX file."
        ) from e

    def local(tag: str) -> str:
        return tag.rsplit("}", 1)[-1]

    pts = [el for el in tree.iter() if local(el.tag) == "trkpt"]
    if not pts:
        raise DriveFormatError(
            f"{path}: GPX has no <trkpt> track points. Export the track (not waypoints/routes)."
        )
    good: list[tuple[int | None, float, float, float, float, float]] = []
    n_bad = 0
    for k, el in enumerate(pts, start=1):
        child = {local(c.tag): (c.text or "").strip() for c in el}
        tag = f"trkpt #{k}"
        try:
            lat, lon = float(el.get("lat", "nan")), float(el.get("lon", "nan"))
        except ValueError:
            lat = lon = math.nan
        why = valid_latlon(lat, lon)
        if why is None and not child.get("time"):
            why = "no <time>"
        t = math.nan
        if why is None:
            try:
                t = _parse_iso_time(child["time"])
            except ValueError:
                why = f"<time> {child['time']!r} is not ISO 8601"
        if why is not None:
            n_bad += 1
            skipped.append(Skipped(path.name, None, f"GPX {tag} dropped: {why}"))
            continue

        good.append((None, t, lat, lon, _num(child, "ele"), _num(child, "hdop")))
    return gps_from_lists(path, good, skipped, n_bad, len(pts), warnings)
