"""Drive loader, obd.csv, and the distance along the drive from OBD else GPS."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive import along_track_m, load_drive
from tests.io.drive_fixtures import LAT0, LON0, make_drive

# --------------------------------------------------------------------------- OBD


def test_obd_optional_and_validated(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "obd.csv").write_text("timestamp_s,speed_mps\n0.0,5.0\n0.1,nan\n0.2,-1\n0.3,5.5\n")
    d = load_drive(root)
    assert d.obd is not None and list(d.obd.speed_mps) == [5.0, 5.5]
    assert [s.line for s in d.skipped if s.file == "obd.csv"] == [3, 4]
    (root / "obd.csv").write_text("timestamp_s,speed_mps\n0.0,5.0\n0.0,5.0\n")
    with pytest.raises(DriveFormatError, match=r"obd.csv:3"):
        load_drive(root)


def test_obd_on_another_clock_is_dropped_with_a_warning(tmp_path: Path) -> None:
    """An OBD logger stamping in its own clock (here 1,000 s off) never meets the frames: its
    speeds would constrain the wrong frames, so it is not used, and the run says so."""
    root = make_drive(tmp_path / "d", n=20)
    rows = "\n".join(f"{1000 + 0.1 * k:.1f},5.0" for k in range(30))
    (root / "obd.csv").write_text("timestamp_s,speed_mps\n" + rows + "\n")
    d = load_drive(root)
    assert d.obd is None
    assert any("OBD times" in w and "do not overlap" in w and "+1000.0 s" in w for w in d.warnings)
    rows = "\n".join(f"{1.5 + 0.1 * k:.1f},5.0" for k in range(30))  # the last quarter only
    (root / "obd.csv").write_text("timestamp_s,speed_mps\n" + rows + "\n")
    d = load_drive(root)
    assert d.obd is not None and any("OBD covers only 21%" in w for w in d.warnings), d.warnings


# --------------------------------------------------------------------------- distance along


def test_along_track_from_obd_else_gps_else_none(tmp_path: Path) -> None:
    """Frames at 10 Hz: OBD speed 5 m/s -> 0.5 m per frame; without OBD the GPS path (fixes
    1e-5 deg of latitude = 1.11 m apart every 0.5 s -> 0.222 m per frame); neither -> None."""
    rows = [f"{0.5 * k - 0.5:.3f},{LAT0 + 1e-5 * k:.8f},{LON0:.8f},100.0,0.8" for k in range(5)]
    root = make_drive(tmp_path / "d", n=8, gps_rows=rows)
    s = along_track_m(load_drive(root))
    assert s is not None and s[0] == 0.0
    np.testing.assert_allclose(np.diff(s), 0.2223, atol=5e-4)
    (root / "obd.csv").write_text("timestamp_s,speed_mps\n0.2,5.0\n0.5,5.0\n")
    s = along_track_m(load_drive(root))
    # frames before and after the OBD log are extrapolated at its end speeds
    assert s is not None
    np.testing.assert_allclose(s, 0.5 * np.arange(8), atol=1e-9)
    assert along_track_m(load_drive(make_drive(tmp_path / "n", gps=None))) is None
