"""Drive loader, GPS logs (gps.csv, gps.gpx, gps.nmea) and their overlap with the frames."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive import load_drive
from tests.io.drive_fixtures import (
    LAT0,
    LON0,
    T0,
    make_drive,
    moving_gps_rows,
    nmea,
    nmea_lines,
)

# --------------------------------------------------------------------------- GPS csv


def test_gps_bad_rows_dropped_and_counted(tmp_path: Path) -> None:
    rows = [
        f"-0.5,{LAT0},{LON0},100,0.9",
        "0.0,nan,-79.4,100,0.9",
        f"0.2,{LAT0},200.0,100,0.9",
        f"0.3,95.0,{LON0},,",
        f"0.4,{LAT0},{LON0},,",
        "0.45,abc,-79.4,,",
        f"1.0,{LAT0},{LON0},,",
    ]
    d = load_drive(make_drive(tmp_path / "d", gps_rows=rows))
    assert d.gps is not None and len(d.gps) == 3
    gps_skips = [s for s in d.skipped if s.file == "gps.csv"]
    assert [s.line for s in gps_skips] == [3, 4, 5, 7]
    assert any("dropped 4 of 7" in w for w in d.warnings)
    assert np.isnan(d.gps.alt_m[1]) and np.isnan(d.gps.hdop[1])


def test_gps_non_increasing_timestamps(tmp_path: Path) -> None:
    rows = [f"0.0,{LAT0},{LON0}", f"0.5,{LAT0},{LON0}", f"0.5,{LAT0 + 1e-5},{LON0}"]
    root = make_drive(tmp_path / "d", gps_rows=rows)
    with pytest.raises(DriveFormatError, match=r"gps.csv:4: GPS timestamp 0.5 is not after"):
        load_drive(root)


def test_gps_not_overlapping_frames_warns_and_drops_gps(tmp_path: Path) -> None:
    rows = [f"{1000 + k},{LAT0},{LON0}" for k in range(5)]
    d = load_drive(make_drive(tmp_path / "d", gps_rows=rows))
    assert d.gps is None
    assert any("do not overlap" in w and "local frame" in w for w in d.warnings)


def test_gps_outage_within_the_frames_warns_naming_times_and_frames(tmp_path: Path) -> None:
    """A tunnel or a dead logger: no fix for 3 s in the middle of the frames (2 Hz log).
    First and last fix still bracket the frames, so only a check inside the log sees it."""
    rows = [r for r in moving_gps_rows(-0.5, 6.5, 5.0) if not 1.2 < float(r.split(",")[0]) < 4.3]
    d = load_drive(make_drive(tmp_path / "d", n=60, gps_rows=rows))
    out = [w for w in d.warnings if "no fix for" in w]
    assert d.gps is not None and len(out) == 1, d.warnings
    assert "3.5 s between 1.00 and 4.50 s (34 frames, 000011.png to 000044.png)" in out[0]
    # a 1 Hz receiver missing one fix (2 s) is no outage
    rows = [r for r in moving_gps_rows(-0.5, 6.5, 5.0, 1.0) if float(r.split(",")[0]) != 2.5]
    d = load_drive(make_drive(tmp_path / "e", n=60, gps_rows=rows))
    assert not [w for w in d.warnings if "no fix for" in w], d.warnings


def test_a_drive_between_sparse_fixes_warns(tmp_path: Path) -> None:
    """A 0.2 Hz log around a 2.3 s drive: one fix inside, the others 2.7 and 5 s beyond its ends."""
    rows = moving_gps_rows(-5.0, 10.0, 5.0, rate_hz=0.2)
    d = load_drive(make_drive(tmp_path / "d", n=24, gps_rows=rows))
    (w,) = [w for w in d.warnings if "fall within" in w]
    assert "only 1 fix(es) fall within the frames' 2.3 s" in w and "up to 5.0 s" in w
    # a 1 Hz log around the same drive: three fixes inside, nothing to say
    d = load_drive(make_drive(tmp_path / "e", n=24, gps_rows=moving_gps_rows(-1, 4, 5.0, 1.0)))
    assert not [w for w in d.warnings if "fall within" in w], d.warnings


def test_gps_partial_overlap_warns(tmp_path: Path) -> None:
    rows = [f"{0.3 + 0.05 * k:.3f},{LAT0},{LON0}" for k in range(5)]
    d = load_drive(make_drive(tmp_path / "d", n=20, gps_rows=rows))
    assert d.gps is not None and any("covers only" in w for w in d.warnings)


def test_no_gps_at_all(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "d", gps=None))
    assert d.gps is None and any("no GPS log" in w for w in d.warnings)


def test_all_gps_rows_bad_gives_no_gps(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "d", gps_rows=["0.0,nan,nan", "0.5,0,0"]))
    assert d.gps is None and len([s for s in d.skipped if s.file == "gps.csv"]) == 2


# --------------------------------------------------------------------------- GPX


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def test_gpx(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    pts = []
    for k in range(4):
        pts.append(
            f'<trkpt lat="{LAT0 + 1e-5 * k}" lon="{LON0}"><ele>{100 + k}</ele>'
            f"<time>{_iso(T0 - 0.5 + 0.5 * k)}</time><hdop>1.2</hdop></trkpt>"
        )
    pts.append(f'<trkpt lat="nan" lon="{LON0}"><time>{_iso(T0 + 2)}</time></trkpt>')
    pts.append(f'<trkpt lat="{LAT0}" lon="{LON0}"></trkpt>')  # no time
    gpx = (
        '<?xml version="1.0"?><gpx version="1.1" xmlns="http://www.topografix.com/GPX/1/1">'
        "<trk><trkseg>" + "".join(pts) + "</trkseg></trk></gpx>"
    )
    (root / "gps.gpx").write_text(gpx)
    d = load_drive(root)
    assert d.gps is not None and d.gps.source == "gps.gpx" and len(d.gps) == 4
    assert d.gps.timestamp_s[1] == pytest.approx(T0, abs=1e-3)
    assert d.gps.alt_m[2] == 102 and d.gps.hdop[0] == 1.2
    assert len([s for s in d.skipped if s.file == "gps.gpx"]) == 2


def test_gpx_relative_frame_times_do_not_overlap(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=0.0, gps=None)
    (root / "gps.gpx").write_text(
        '<gpx><trk><trkseg><trkpt lat="43.6" lon="-79.4"><time>2023-11-14T22:13:20Z</time>'
        '</trkpt><trkpt lat="43.6" lon="-79.4"><time>2023-11-14T22:13:21Z</time></trkpt>'
        "</trkseg></trk></gpx>"
    )
    d = load_drive(root)
    assert d.gps is None and any("UNIX seconds" in w for w in d.warnings)


def test_gpx_broken_xml(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", gps=None)
    (root / "gps.gpx").write_text("<gpx><trk>\n<trkseg>")
    with pytest.raises(DriveFormatError, match="not valid XML"):
        load_drive(root)


# --------------------------------------------------------------------------- NMEA


def test_nmea_rmc_gga_checksum(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    lines = nmea_lines(T0 - 0.5, 4, alt_step_m=1.0)
    good_rmc = lines[2]
    lines[2] = good_rmc[:-2] + ("00" if good_rmc[-2:] != "00" else "11")  # bad checksum
    lines.append("$GPGSV,3,1,11,03,03,111,00,04,15,270,00,06,01,010,00,13,06,292,00*74")
    lines.append("garbage line")
    (root / "gps.nmea").write_text("\n".join(lines) + "\n")
    d = load_drive(root)
    assert d.gps is not None and d.gps.source == "gps.nmea"
    assert len(d.gps) == 4  # fix 1 keeps its GGA although its RMC was rejected
    assert d.gps.timestamp_s[1] == pytest.approx(T0, abs=0.02)
    assert d.gps.lat_deg[3] == pytest.approx(LAT0 + 3e-5, abs=1e-7)
    assert d.gps.lon_deg[0] == pytest.approx(LON0, abs=1e-7)
    # GGA altitude is above mean sea level; + the geoid separation (-34 m) = ellipsoidal height
    assert d.gps.hdop[0] == pytest.approx(0.9) and d.gps.alt_m[2] == pytest.approx(122.0 - 34.0)
    assert d.gps.alt_datum == "WGS84 ellipsoidal height"
    (s,) = [s for s in d.skipped if s.file == "gps.nmea"]
    assert s.line == 3 and "checksum" in s.reason


def test_nmea_without_rmc_is_an_error(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", gps=None)
    (root / "gps.nmea").write_text(
        nmea("GPGGA,120000.00,4336.0000,N,07924.0000,W,1,08,0.9,120.0,M,-34.0,M,,") + "\n"
    )
    with pytest.raises(DriveFormatError, match="no valid \\$GPRMC"):
        load_drive(root)


def test_gps_verbatim_duplicate_row_is_dropped_not_fatal(tmp_path: Path) -> None:
    rows = [f"0.0,{LAT0},{LON0}", f"0.5,{LAT0},{LON0}", f"0.5,{LAT0},{LON0}", f"1.0,{LAT0},{LON0}"]
    d = load_drive(make_drive(tmp_path / "d", gps_rows=rows))
    assert d.gps is not None and len(d.gps) == 3
    (s,) = [s for s in d.skipped if s.file == "gps.csv"]
    assert s.line == 4 and "duplicate" in s.reason
    # the warning says what they were (it read "bad or out-of-range values")
    assert any("repeat the previous one verbatim" in w for w in d.warnings)
    assert not any("bad or out-of-range" in w for w in d.warnings)
