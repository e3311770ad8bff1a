"""A GPS log's own statement of its accuracy: gps.csv 'sigma_m' / 'fix_quality', NMEA GST and
GGA fix quality, and how the pose graph weighs the fixes by them (mapping.pose_gps)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.io.drive import load_drive
from roadsurf.io.drive.types import GpsTrack
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.pose_gps import fix_sigma_m
from tests.io.drive_fixtures import LAT0, LON0, T0, make_drive, nmea_lines


def _csv(root: Path, header: str, rows: list[str]) -> Path:
    (root / "gps.csv").write_text(header + "\n" + "\n".join(rows) + "\n")
    return root


def test_csv_sigma_and_fix_quality_columns_are_read(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    rows = [
        f"{-0.5 + 0.5 * k:.1f},{LAT0 + 1e-6 * k:.8f},{LON0},100,0.8,{s},{q}"
        for k, (s, q) in enumerate([("0.02", "4"), ("", "5"), ("0.5", ""), ("", "")])
    ]
    d = load_drive(_csv(root, "timestamp_s,lat,lon,alt_m,hdop,sigma_m,fix_quality", rows))
    g = d.gps
    assert g is not None
    assert g.sigma_m[0] == pytest.approx(0.02) and g.sigma_m[2] == pytest.approx(0.5)
    assert np.isnan(g.sigma_m[[1, 3]]).all()
    assert g.quality.tolist() == [4, 5, 0, 0]
    assert g.states_accuracy
    # the pose graph's σ with gps_sigma_from_log: stated > RTK quality > HDOP
    cfg = MappingConfig(gps_sigma_from_log=True)
    assert fix_sigma_m(cfg, g).tolist() == pytest.approx(
        [0.02, cfg.gps_sigma_rtk_float_m, 0.5, 0.8 * cfg.gps_sigma_per_hdop_m]
    )
    # by default HDOP only (the stated σ is read, not used: docs/mapping.md)
    assert fix_sigma_m(MappingConfig(), g) == pytest.approx(0.8 * cfg.gps_sigma_per_hdop_m)


def test_a_log_without_accuracy_columns_states_none(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "d"))
    assert d.gps is not None and not d.gps.states_accuracy
    assert np.isnan(d.gps.sigma_m).all() and (d.gps.quality == 0).all()
    sig = fix_sigma_m(MappingConfig(), d.gps)
    assert sig == pytest.approx(0.8 * MappingConfig().gps_sigma_per_hdop_m)


@pytest.mark.parametrize(
    ("col", "value"), [("sigma_m", "-0.1"), ("sigma_m", "0.000"), ("sigma_m", "20000"),
                       ("sigma_m", "abc"), ("fix_quality", "4.5")],
)  # fmt: skip
def test_bad_accuracy_value_is_not_stated_and_named(tmp_path: Path, col: str, value: str) -> None:
    """The columns are optional and unused by default: a log that loaded before they were read
    still loads; the bad value counts as not stated and one warning names its line."""
    root = make_drive(tmp_path / "d")
    good = "0.02" if col == "sigma_m" else "4"
    rows = [f"{-0.5 + 0.5 * k:.1f},{LAT0 + 1e-6 * k:.8f},{LON0},{value if k == 2 else good}"
            for k in range(4)]  # fmt: skip
    _csv(root, f"timestamp_s,lat,lon,{col}", rows)
    d = load_drive(root)
    assert d.gps is not None and len(d.gps) == 4
    (w,) = [w for w in d.warnings if "not valid" in w]
    assert "on 1 row(s) (line 4)" in w and "taken as not stated" in w, w
    if col == "sigma_m":
        assert np.isnan(d.gps.sigma_m[2]) and np.isfinite(d.gps.sigma_m[[0, 1, 3]]).all()


def test_nmea_gst_gives_each_fix_its_sigma(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    lines = nmea_lines(T0 - 0.5, 4, quality=4, gst_offset_s=0.0)
    lines[5] = lines[5][:-2] + ("00" if lines[5][-2:] != "00" else "11")  # one GST corrupted
    (root / "gps.nmea").write_text("\n".join(lines) + "\n")
    d = load_drive(root)
    g = d.gps
    assert g is not None and len(g) == 4
    rms = np.sqrt(0.5 * (0.03**2 + 0.04**2))
    assert g.sigma_m[[0, 2, 3]] == pytest.approx(rms) and np.isnan(g.sigma_m[1])
    assert (g.quality == 4).all()
    # a sentence failing its checksum is garbled data, said with its line
    assert any("garbled" in w and "(line 6)" in w for w in d.warnings)
    # the fix without its GST falls back on its RTK fixed quality
    cfg = MappingConfig(gps_sigma_from_log=True)
    sig = fix_sigma_m(cfg, g)
    assert sig[1] == pytest.approx(cfg.gps_sigma_rtk_fixed_m)
    assert sig[0] == pytest.approx(rms)


def test_nmea_gst_without_checksum_is_read(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    lines = [
        ln.rsplit("*", 1)[0] if ln.startswith("$GPGST") else ln
        for ln in nmea_lines(T0 - 0.5, 4, gst_offset_s=0.0)
    ]
    (root / "gps.nmea").write_text("\n".join(lines) + "\n")
    g = load_drive(root).gps
    assert g is not None and np.isfinite(g.sigma_m).all()
    # a GGA quality of 1 (GPS) states no accuracy; a GST does
    assert g.states_accuracy and (g.quality == 1).all()


def test_nmea_gst_at_other_times_warns(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    (root / "gps.nmea").write_text("\n".join(nmea_lines(T0 - 0.5, 4, gst_offset_s=0.25)) + "\n")
    d = load_drive(root)
    assert d.gps is not None and np.isnan(d.gps.sigma_m).all()
    assert any("GST sentence(s)" in w and "match no RMC/GGA" in w for w in d.warnings)
    assert not d.gps.states_accuracy  # GGA quality 1 and no matching GST


def test_gps_track_without_accuracy_fields_fills_them() -> None:
    g = GpsTrack(np.arange(3.0), np.full(3, LAT0), np.full(3, LON0), np.full(3, np.nan),
                 np.full(3, np.nan))  # fmt: skip
    assert g.sigma_m.shape == (3,) and np.isnan(g.sigma_m).all()
    assert g.quality.tolist() == [0, 0, 0] and not g.states_accuracy
