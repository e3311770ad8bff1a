"""NMEA read with pynmea2 and resynchronised after binary data; GPX read with gpxpy; the vertical
datum of the heights (GGA MSL + geoid separation = ellipsoidal; GPX <ele> orthometric)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.io.drive import load_drive
from roadsurf.io.drive.types import ALT_ELLIPSOIDAL, ALT_GPX_ELE, ALT_MSL, ALT_NONE
from tests.io.drive_fixtures import LAT0, T0, gpx_text, make_drive, nmea_lines

UBX = bytes([0xB5, 0x62, 0x01, 0x07, 0x5C, 0x00, 0x24, 0x0A, 0xFF, 0x00, 0x13, 0x80, 0x0D])


def _nmea_drive(tmp_path: Path, data: bytes) -> Path:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    (root / "gps.nmea").write_bytes(data)
    return root


def test_nmea_sentences_after_ubx_binary_on_the_same_line_are_read(tmp_path: Path) -> None:
    """The old parser dropped every line that did not start with '$': here 3 of the 4 fixes sit
    behind UBX bytes (which even hold a '$' and a newline) on their line."""
    lines = [s.encode() for s in nmea_lines(T0 - 0.5, 4)]
    data = lines[0] + b"\r\n" + lines[1] + b"\r\n"
    for k in range(1, 4):
        data += UBX + lines[2 * k] + b"\r\n" + UBX[:5] + lines[2 * k + 1] + UBX[-4:] + b"\r\n"
    d = load_drive(_nmea_drive(tmp_path, data))
    assert d.gps is not None and len(d.gps) == 4
    np.testing.assert_allclose(d.gps.lat_deg, LAT0 + 1e-5 * np.arange(4), atol=1e-7)
    (w,) = [w for w in d.warnings if "binary or garbled" in w]
    # per fix: the UBX bytes, 5 before the GGA and 4 after it, less the 3 whitespace bytes (the
    # UBX 0x0A and two 0x0D before line ends) that are not counted
    n_bytes = 3 * (len(UBX) + 5 + 4 - 3)
    assert f"skipped {n_bytes} byte(s)" in w and "6 sentence(s)" in w
    assert not [s for s in d.skipped if s.file == "gps.nmea"]


def test_nmea_garbled_sentence_is_counted_not_fatal(tmp_path: Path) -> None:
    lines = nmea_lines(T0 - 0.5, 4)
    lines[2] = lines[2][:20] + "\x00\x01" + lines[2][20:]  # RMC cut by binary: malformed
    d = load_drive(_nmea_drive(tmp_path, "\n".join(lines).encode("latin-1")))
    assert d.gps is not None and len(d.gps) == 4  # fix 1 keeps its GGA
    assert [s.reason for s in d.skipped if s.file == "gps.nmea"] == ["malformed NMEA sentence"]
    assert any("binary or garbled" in w for w in d.warnings)


def test_nmea_clean_log_has_no_warning(tmp_path: Path) -> None:
    d = load_drive(_nmea_drive(tmp_path, ("\r\n".join(nmea_lines(T0 - 0.5, 4)) + "\r\n").encode()))
    assert d.gps is not None and len(d.gps) == 4 and d.warnings == []


def test_nmea_height_is_msl_plus_geoid_separation(tmp_path: Path) -> None:
    d = load_drive(
        _nmea_drive(tmp_path, "\n".join(nmea_lines(T0 - 0.5, 4, geoid_sep="-34.5")).encode())
    )
    assert d.gps is not None and d.gps.alt_datum == ALT_ELLIPSOIDAL
    np.testing.assert_allclose(d.gps.alt_m, 120.0 - 34.5)


def test_nmea_without_geoid_separation_warns_heights_are_msl(tmp_path: Path) -> None:
    d = load_drive(_nmea_drive(tmp_path, "\n".join(nmea_lines(T0 - 0.5, 4, geoid_sep="")).encode()))
    assert d.gps is not None and d.gps.alt_datum == ALT_MSL
    np.testing.assert_allclose(d.gps.alt_m, 120.0)
    assert any("mean sea level" in w and "geoid separation" in w for w in d.warnings)


def test_nmea_partly_missing_geoid_separation_uses_the_others(tmp_path: Path) -> None:
    lines = nmea_lines(T0 - 0.5, 4, geoid_sep="-34.0")
    lines[3] = nmea_lines(T0, 1, geoid_sep="")[1]  # fix 1's GGA without field 11
    d = load_drive(_nmea_drive(tmp_path, "\n".join(lines).encode()))
    assert d.gps is not None and d.gps.alt_datum == ALT_ELLIPSOIDAL
    np.testing.assert_allclose(d.gps.alt_m, 86.0)
    assert any("1 GGA fix(es) lack the geoid separation" in w for w in d.warnings)


def test_gpx_ele_datum_and_warning(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    (root / "gps.gpx").write_text(gpx_text(T0 - 0.5, 4))
    d = load_drive(root)
    assert d.gps is not None and d.gps.alt_datum == ALT_GPX_ELE
    np.testing.assert_allclose(d.gps.alt_m, [100, 101, 102, 103])
    assert d.gps.timestamp_s[1] == pytest.approx(T0, abs=1e-6)
    assert any("<ele>" in w and "not WGS84 ellipsoidal" in w for w in d.warnings)
    (root / "gps.gpx").write_text(gpx_text(T0 - 0.5, 4, ele=False))
    d = load_drive(root)
    assert d.gps is not None and d.gps.alt_datum == ALT_NONE and d.warnings == []


def test_gps_csv_heights_are_ellipsoidal(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "d"))
    assert d.gps is not None and d.gps.alt_datum == ALT_ELLIPSOIDAL


def test_gpx_invalid_value_is_one_line_error(tmp_path: Path) -> None:
    from roadsurf.core.errors import DriveFormatError

    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    (root / "gps.gpx").write_text(gpx_text(T0 - 0.5, 4).replace("<ele>101</ele>", "<ele>x</ele>"))
    with pytest.raises(DriveFormatError, match="gps.gpx: GPX has an invalid value") as e:
        load_drive(root)
    assert "\n" not in str(e.value)


def test_nmea_without_checksums_is_read_with_a_warning(tmp_path: Path) -> None:
    """A logger that strips the '*hh' checksums: the sentences are read (they were all dropped
    as 'malformed'), and one warning says they went unchecked. A sentence cut by binary data
    stays malformed."""
    lines = [s[: s.rindex("*")] for s in nmea_lines(T0 - 0.5, 4)]
    d = load_drive(_nmea_drive(tmp_path, ("\r\n".join(lines) + "\r\n").encode()))
    assert d.gps is not None and len(d.gps) == 4
    np.testing.assert_allclose(d.gps.lat_deg, LAT0 + 1e-5 * np.arange(4), atol=1e-7)
    (w,) = [w for w in d.warnings if "no checksum" in w]
    assert "8 of 8 RMC/GGA sentences" in w
    assert not [s for s in d.skipped if s.file == "gps.nmea"]


def test_nmea_gga_before_midnight_logged_before_the_first_rmc_keeps_its_day(
    tmp_path: Path,
) -> None:
    """A log whose RMC output starts only after 00:00 UTC: the GGA fixes before midnight take
    the day before the first RMC's date, not its date (they were put 24 h late, a helper's
    battery: half the fixes off the frames' clock)."""
    import calendar
    from datetime import datetime

    from roadsurf.io.drive.nmea import load_gps_nmea

    t0 = calendar.timegm(datetime(2026, 6, 16).timetuple()) - 2.0  # 23:59:58 on 15 June
    lines = nmea_lines(t0, 10)
    # the RMC sentences of the fixes before midnight are missing (RMC output enabled late)
    lines = [s for k, s in enumerate(lines) if not (k % 2 == 0 and k // 2 < 4)]
    p = tmp_path / "gps.nmea"
    p.write_text("\n".join(lines) + "\n")
    g = load_gps_nmea(p, [], [])
    assert g is not None
    assert np.allclose(g.timestamp_s, t0 + 0.5 * np.arange(10), atol=1e-3)
