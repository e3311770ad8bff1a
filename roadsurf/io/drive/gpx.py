"""gps.gpx: track points (<trkpt> with lat/lon, <time>, optional <ele> and <hdop>), read with
gpxpy. <ele> is kept as written: by GPX convention it is a height above the geoid (mean sea
level) as the device models it, not a WGS84 ellipsoidal height; the track says so in its
``alt_datum`` and a warning."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from datetime import UTC
from pathlib import Path

import gpxpy
import gpxpy.gpx
import numpy as np

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive.gps import gps_from_lists, valid_latlon
from roadsurf.io.drive.textfile import read_text
from roadsurf.io.drive.types import ALT_GPX_ELE, GpsTrack, Skipped


def _float(v: float | None) -> float:
    return math.nan if v is None else float(v)


def _parse(path: Path) -> gpxpy.gpx.GPX:
    text = read_text(path)  # non-UTF-8 bytes: a one-line error naming the line
    try:
        return gpxpy.parse(text)
    except gpxpy.gpx.GPXXMLSyntaxException as e:
        orig = e.__cause__
        pos = getattr(orig, "position", None) if isinstance(orig, ET.ParseError) else None
        at = f"{path}:{pos[0]}" if pos else str(path)
        raise DriveFormatError(
            f"{at}: not valid XML ({orig or e}). Fix or re-export the GPX file."
        ) from e
    except (gpxpy.gpx.GPXException, ValueError, OverflowError) as e:
        # gpxpy checks every value it reads: one bad <time>, lat or <ele> fails the whole file.
        msg = " ".join(str(e).split())[:200]
        raise DriveFormatError(
            f"{path}: GPX has an invalid value ({msg}). Fix the point or re-export the GPX file."
        ) from e


def load_gps_gpx(path: Path, skipped: list[Skipped], warnings: list[str]) -> GpsTrack | None:
    gpx = _parse(path)
    pts = [p for trk in gpx.tracks for seg in trk.segments for p in seg.points]
    if not pts:
        raise DriveFormatError(
            f"{path}: GPX has no <trkpt> track points. Export the track (not waypoints/routes)."
        )
    good: list[tuple[int | None, float, float, float, float, float]] = []
    n_bad = 0
    for k, p in enumerate(pts, start=1):
        lat, lon = _float(p.latitude), _float(p.longitude)
        why = valid_latlon(lat, lon)
        if why is None and p.time is None:
            why = "no <time>, or one that is not ISO 8601"  # gpxpy reads a bad time as none
        t = math.nan
        if why is None and p.time is not None:
            tm = p.time if p.time.tzinfo is not None else p.time.replace(tzinfo=UTC)
            try:
                t = tm.timestamp()
            except (ValueError, OverflowError):
                why = f"<time> {p.time!s} is out of range"
        if why is not None:
            n_bad += 1
            skipped.append(Skipped(path.name, None, f"GPX trkpt #{k} dropped: {why}"))
            continue
        good.append((None, t, lat, lon, _float(p.elevation), _float(p.horizontal_dilution)))
    if good and np.isfinite([g[4] for g in good]).any():
        warnings.append(
            f"{path}: GPX <ele> heights are used as written; by GPX convention they are above "
            f"the geoid (mean sea level, as modelled by the device), not WGS84 ellipsoidal "
            f"heights, and may differ by tens of metres. For ellipsoidal heights use gps.csv "
            f"(alt_m ellipsoidal) or NMEA GGA with the geoid separation."
        )
    return gps_from_lists(path, good, skipped, n_bad, len(pts), warnings, alt_datum=ALT_GPX_ELE)
