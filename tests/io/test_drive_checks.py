"""Plausibility checks of the loader: OBD vs GPS speed (km/h for m/s), impossible GPS jumps
(hemisphere flip, UTM zone), no usable GPS said plainly, a static receiver."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.io.drive import load_drive
from tests.io.drive_fixtures import LAT0, LON0, make_drive, moving_gps_rows

N, DT = 61, 0.1  # 6 s of frames


def _drive(tmp_path: Path, gps_rows: list[str], obd_speed: float | None = None) -> Path:
    root = make_drive(tmp_path / "d", n=N, gps_rows=gps_rows)
    if obd_speed is not None:
        rows = [f"{0.1 * k:.2f},{obd_speed}" for k in range(61)]
        (root / "obd.csv").write_text("timestamp_s,speed_mps\n" + "\n".join(rows) + "\n")
    return root


@pytest.mark.parametrize("speed", [10.0, 20.0])
def test_obd_agreeing_with_gps_is_used_silently(tmp_path: Path, speed: float) -> None:
    d = load_drive(_drive(tmp_path, moving_gps_rows(-0.5, 6.5, speed), obd_speed=speed * 1.1))
    assert d.obd is not None and d.warnings == []


def test_obd_in_kmh_is_converted_with_a_warning(tmp_path: Path) -> None:
    d = load_drive(_drive(tmp_path, moving_gps_rows(-0.5, 6.5, 10.0), obd_speed=36.0))
    assert d.obd is not None
    np.testing.assert_allclose(d.obd.speed_mps, 10.0)
    (w,) = d.warnings
    assert "km/h" in w and "divided by 3.6" in w and "ratio 3.60" in w


def test_obd_disagreeing_with_gps_is_ignored(tmp_path: Path) -> None:
    d = load_drive(_drive(tmp_path, moving_gps_rows(-0.5, 6.5, 10.0), obd_speed=14.0))
    assert d.obd is None
    (w,) = d.warnings
    assert "+40 %" in w and "OBD log is ignored" in w and "OBD 14.00 m/s vs GPS 9.99 m/s" in w


def _turning_gps_rows(speed: float, radius: float) -> list[str]:
    """gps.csv rows at 2 Hz of a receiver turning on a circle (a U-turn and beyond in 7 s)."""
    rows = []
    for k in range(15):
        t = -0.5 + 0.5 * k
        a = speed * (t + 0.5) / radius  # angle turned (rad)
        north, east = radius * np.sin(a), radius * (1 - np.cos(a))
        lon = LON0 + east / (111_195.0 * np.cos(np.radians(LAT0)))
        rows.append(f"{t:.3f},{LAT0 + north / 111_195.0:.9f},{lon:.9f},100.0,0.8")
    return rows


@pytest.mark.parametrize("speed", [6.0, 6.0 * 3.6])
def test_obd_on_a_turn_is_judged_along_the_path(tmp_path: Path, speed: float) -> None:
    """On a U-turn (radius 8 m, 6 m/s) the chords are far shorter than the road driven: a right
    m/s log was ignored (ratio 2.3), and beyond a U-turn divided by 3.6. Along the path it is
    used, and a km/h log is still converted."""
    d = load_drive(_drive(tmp_path, _turning_gps_rows(6.0, 8.0), obd_speed=speed))
    assert d.obd is not None
    np.testing.assert_allclose(d.obd.speed_mps, 6.0)
    assert [w for w in d.warnings if "OBD" in w] == ([] if speed == 6.0 else d.warnings[:1])


def _flip(row: str, lat_sign: float = 1.0, dlon: float = 0.0) -> str:
    t, lat, lon, *rest = row.split(",")
    return ",".join([t, f"{lat_sign * float(lat):.9f}", f"{float(lon) + dlon:.9f}", *rest])


def test_hemisphere_flip_and_utm_zone_jump_are_rejected(tmp_path: Path) -> None:
    rows = moving_gps_rows(-0.5, 6.5, 10.0)
    rows[4] = _flip(rows[4], lat_sign=-1.0)  # gps.csv line 6
    rows[9] = _flip(rows[9], dlon=6.0)  # line 11: converted in the next UTM zone
    d = load_drive(_drive(tmp_path, rows))
    assert d.gps is not None and len(d.gps) == len(rows) - 2
    assert (d.gps.lat_deg > 0).all() and np.allclose(d.gps.lon_deg, LON0)
    (w,) = [w for w in d.warnings if "rejected 2 of 15 GPS fix(es)" in w]
    assert "line 6" in w and "hemisphere flip" in w and "line 11" in w
    assert "UTM zone jump 17 -> 18" in w
    assert [s.line for s in d.skipped if s.file == "gps.csv"] == [6, 11]


def test_a_wrong_first_fix_is_the_one_rejected(tmp_path: Path) -> None:
    rows = moving_gps_rows(-0.5, 6.5, 10.0)
    rows[0] = _flip(rows[0], lat_sign=-1.0)
    d = load_drive(_drive(tmp_path, rows))
    assert d.gps is not None and len(d.gps) == len(rows) - 1 and d.gps.lat_deg[0] > 0
    assert any("line 2" in w and "hemisphere flip" in w for w in d.warnings)


def test_no_usable_gps_says_no_georeference(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "a", gps_rows=["0.0,nan,nan", "0.5,0,0"]))
    assert d.gps is None
    assert any("NO GEOREFERENCE" in w and "no lon/lat outputs" in w for w in d.warnings)
    rows = [f"{1000 + k},{LAT0},{LON0}" for k in range(5)]
    d = load_drive(make_drive(tmp_path / "b", gps_rows=rows))
    assert d.gps is None
    assert any("do not overlap" in w and "NO GEOREFERENCE" in w for w in d.warnings)


def test_static_receiver_warns(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    rows = [
        f"{-0.5 + 0.5 * k:.3f},{LAT0 + rng.normal(0, 1e-5):.9f},{LON0 + rng.normal(0, 1e-5):.9f},"
        f"100.0,0.9"
        for k in range(15)
    ]
    d = load_drive(_drive(tmp_path, rows, obd_speed=10.0))
    (w,) = d.warnings
    assert "static receiver" in w and "over 6.0 s of frames" in w
    assert d.obd is not None  # a static GPS does not judge the OBD speed


def test_short_or_moving_drives_are_not_static(tmp_path: Path) -> None:
    assert load_drive(_drive(tmp_path / "m", moving_gps_rows(-0.5, 6.5, 3.0))).warnings == []
    rows = [f"{-0.5 + 0.5 * k:.3f},{LAT0},{LON0},100.0,0.9" for k in range(4)]
    assert load_drive(make_drive(tmp_path / "s", gps_rows=rows)).warnings == []


def test_slow_vehicles_are_not_static(tmp_path: Path) -> None:
    """1 m/s for 6 s stays within HDOP's 3 σ (8 m) but the fixes progress; an RTK log's stated
    σ of 2 cm is its noise, not HDOP's metres. A frozen RTK receiver still warns."""
    assert load_drive(_drive(tmp_path / "c", moving_gps_rows(-0.5, 6.5, 1.0))).warnings == []
    rtk = [f"{r},0.02" for r in moving_gps_rows(-0.5, 6.5, 0.3, rate_hz=10.0)]
    root = make_drive(tmp_path / "r", n=N)
    (root / "gps.csv").write_text("timestamp_s,lat,lon,alt_m,hdop,sigma_m\n" + "\n".join(rtk))
    assert load_drive(root).warnings == []
    frozen = [f"{-0.5 + 0.1 * k:.3f},{LAT0},{LON0},100.0,0.9,0.02" for k in range(71)]
    (root / "gps.csv").write_text("timestamp_s,lat,lon,alt_m,hdop,sigma_m\n" + "\n".join(frozen))
    (w,) = load_drive(root).warnings
    assert "static receiver" in w and "stated by the log" in w


def test_frame_times_in_milliseconds_warn_against_the_fps(tmp_path: Path) -> None:
    """frames.csv in ms (every interval 100 "s" at fps 10) warns, naming the unit; the camera's
    own rate and frames kept every 5th do not."""
    root = make_drive(tmp_path / "d", n=N, gps_rows=moving_gps_rows(-0.5, 6.5, 10.0))
    d = load_drive(root)
    assert not [w for w in d.warnings if "frame interval" in w]
    lines = (root / "frames.csv").read_text().splitlines()
    thinned = [lines[0], *lines[1::5]]
    (root / "frames.csv").write_text("\n".join(thinned) + "\n")
    assert not [w for w in load_drive(root).warnings if "frame interval" in w]
    ms = [lines[0]] + [f"{r.split(',')[0]},{1000 * float(r.split(',')[1]):.1f}" for r in lines[1:]]
    (root / "frames.csv").write_text("\n".join(ms) + "\n")
    (w,) = [w for w in load_drive(root).warnings if "frame interval" in w]
    assert "100 s" in w and "milliseconds" in w and "frames.csv" in w


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_obd_at_low_speed_with_noisy_gps_is_kept(tmp_path: Path, seed: int) -> None:
    """2 m/s with fixes scattered by σ 2 m (HDOP 0.8 stated): 1 s steps along the path read the
    noise as distance (ratio 0.49, the right log ignored); steps 5 σ long at the chord's speed
    do not."""
    rng = np.random.default_rng(seed)
    rows = []
    for r in moving_gps_rows(-0.5, 30.0, 2.0, rate_hz=1.0):
        t, lat, lon, *rest = r.split(",")
        dn, de = rng.normal(0.0, 2.0, 2)
        lat_n = float(lat) + dn / 111_195.0
        lon_n = float(lon) + de / (111_195.0 * np.cos(np.radians(LAT0)))
        rows.append(",".join([t, f"{lat_n:.9f}", f"{lon_n:.9f}", *rest]))
    root = make_drive(tmp_path / "d", n=301, gps_rows=rows)
    obd = [f"{0.1 * k:.2f},2.0" for k in range(301)]
    (root / "obd.csv").write_text("timestamp_s,speed_mps\n" + "\n".join(obd) + "\n")
    d = load_drive(root)
    assert d.obd is not None and not [w for w in d.warnings if "OBD" in w], d.warnings
