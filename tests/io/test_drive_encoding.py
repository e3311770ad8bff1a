"""One non-UTF-8 byte in any text file of a drive: a one-line DriveFormatError naming the file
and line (and saying to save as UTF-8), never a UnicodeDecodeError. NMEA may hold binary: there
the bytes are skipped with a warning."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive import load_drive
from tests.io.drive_fixtures import T0, gpx_text, make_drive, nmea_lines


def _latin1_on_line(path: Path, line: int) -> None:
    """Put a Latin-1 'é' (0xE9, not UTF-8) at the end of a line (1-based)."""
    rows = path.read_bytes().split(b"\n")
    rows[line - 1] = rows[line - 1] + (b" # caf\xe9" if path.suffix == ".yaml" else b"")
    if path.suffix != ".yaml":
        rows[line - 1] = rows[line - 1].replace(b"0", b"\xe9", 1) if line > 1 else b"\xe9" + rows[0]
    path.write_bytes(b"\n".join(rows))


@pytest.mark.parametrize(
    ("name", "line"),
    [
        ("camera.yaml", 3),
        ("frames.csv", 1),
        ("frames.csv", 4),
        ("gps.csv", 3),
        ("obd.csv", 2),
        ("gps.gpx", 5),
    ],
)
def test_non_utf8_byte_is_a_one_line_error(tmp_path: Path, name: str, line: int) -> None:
    gps = "csv" if name == "gps.csv" else None
    root = make_drive(tmp_path / "d", t0=T0 if name == "gps.gpx" else 0.0, gps=gps)
    if name == "obd.csv":
        (root / "obd.csv").write_text("timestamp_s,speed_mps\n0.0,0.1\n0.1,0.1\n")
    if name == "gps.gpx":
        (root / "gps.gpx").write_text(gpx_text(T0 - 0.5, 4))
    _latin1_on_line(root / name, line)
    with pytest.raises(DriveFormatError) as e:
        load_drive(root)
    msg = str(e.value)
    assert f"{name}:{line}: byte 0xE9" in msg and "Save the file as UTF-8" in msg
    assert "\n" not in msg


def test_utf8_bom_is_accepted(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    for name in ("camera.yaml", "frames.csv", "gps.csv"):
        p = root / name
        p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    d = load_drive(root)
    assert d.gps is not None and len(d.frames) == 5


def test_non_utf8_bytes_in_nmea_are_skipped_with_a_warning(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    lines = [s.encode() for s in nmea_lines(T0 - 0.5, 4)]
    lines.insert(3, b"caf\xe9 \xff\xfe")
    (root / "gps.nmea").write_bytes(b"\n".join(lines))
    d = load_drive(root)
    assert d.gps is not None and len(d.gps) == 4
    assert any("skipped 7 byte(s) of binary" in w and "line 4" in w for w in d.warnings)


def test_csv_syntax_error_is_one_line(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "obd.csv").write_text("timestamp_s,speed_mps\n0.0," + "x" * 200_000 + "\n")
    with pytest.raises(DriveFormatError, match=r"obd.csv:\d+: not valid CSV"):
        load_drive(root)
