"""Drive loader: every validation rule in docs/formats.md, on tiny drives built in tmp_path."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
import pytest

from roadsurf.core.errors import DriveFormatError, FrameReadError
from roadsurf.io.drive import load_drive, read_gray, read_image

W, H = 64, 48
T0 = 1_700_000_000.0  # UNIX seconds (used for GPX/NMEA drives)
LAT0, LON0 = 43.6, -79.4


def camera_yaml(**over: object) -> str:
    vals: dict[str, object] = {
        "model": "pinhole",
        "width": W,
        "height": H,
        "fx": 60.0,
        "fy": 60.0,
        "cx": 32.0,
        "cy": 24.0,
        "dist": [0.0, 0.0, 0.0, 0.0, 0.0],
        "height_m": 1.1,
        "fps": 10,
    }
    vals.update(over)
    return "".join(f"{k}: {v}\n" for k, v in vals.items() if v is not None)


def texture(seed: int, gray: bool = False) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, size=(H, W) if gray else (H, W, 3), dtype=np.uint8)
    return img


def make_drive(
    root: Path,
    n: int = 5,
    ext: str = ".png",
    t0: float = 0.0,
    gps: str | None = "csv",
    gps_rows: list[str] | None = None,
) -> Path:
    """n frames at 10 Hz from t0; GPS at 2 Hz covering the frames."""
    (root / "frames").mkdir(parents=True)
    (root / "camera.yaml").write_text(camera_yaml())
    rows = ["filename,timestamp_s"]
    for i in range(n):
        name = f"{i:06d}{ext}"
        cv2.imwrite(str(root / "frames" / name), texture(i))
        rows.append(f"{name},{t0 + 0.1 * i:.3f}")
    (root / "frames.csv").write_text("\n".join(rows) + "\n")
    if gps == "csv":
        if gps_rows is None:
            gps_rows = [
                f"{t0 + 0.5 * k - 0.5:.3f},{LAT0 + 1e-6 * k:.8f},{LON0:.8f},100.0,0.8"
                for k in range(int(n * 0.2) + 3)
            ]
        (root / "gps.csv").write_text("timestamp_s,lat,lon,alt_m,hdop\n" + "\n".join(gps_rows))
    return root


# --------------------------------------------------------------------------- happy paths


def test_valid_drive_loads(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "d"))
    assert len(d.frames) == 5
    assert [f.index for f in d.frames] == list(range(5))
    assert d.camera.width == W and d.camera.fx == 60.0 and d.camera.height_m == 1.1
    assert d.gps is not None and len(d.gps) >= 3 and d.gps.source == "gps.csv"
    assert np.all(np.isfinite(d.gps.hdop))
    assert d.skipped == []
    assert d.obd is None


def test_read_image_rgb_and_gray_for_colour_and_grey_files(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", n=2, ext=".png")
    grey = texture(7, gray=True)
    cv2.imwrite(str(root / "frames" / "000001.png"), grey)
    d = load_drive(root)
    colour = read_image(d.frames[0])
    assert colour.shape == (H, W, 3) and colour.dtype == np.uint8
    # cv2 wrote BGR; read_image must return RGB.
    bgr = texture(0)
    assert np.array_equal(colour, bgr[:, :, ::-1])
    g3 = read_image(d.frames[1])
    assert g3.shape == (H, W, 3) and np.array_equal(g3[:, :, 0], grey)
    g = read_gray(d.frames[1])
    assert g.shape == (H, W) and g.dtype == np.uint8 and np.array_equal(g, grey)
    assert read_gray(d.frames[0]).shape == (H, W)


def test_jpeg_drive_loads(tmp_path: Path) -> None:
    d = load_drive(make_drive(tmp_path / "d", ext=".jpg"))
    assert len(d.frames) == 5 and read_image(d.frames[2]).shape == (H, W, 3)


def test_dist_optional_defaults_to_zero(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(dist=None))
    cam = load_drive(root).camera
    assert cam.dist == (0.0,) * 5 and not cam.has_distortion
    (root / "camera.yaml").write_text(camera_yaml(dist="[-0.1, 0.01, 0.0, 0.0, 0.001]"))
    assert load_drive(root).camera.dist == (-0.1, 0.01, 0.0, 0.0, 0.001)


# --------------------------------------------------------------------------- camera.yaml


def test_missing_camera_yaml(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").unlink()
    with pytest.raises(DriveFormatError, match="camera.yaml not found"):
        load_drive(root)


def test_missing_camera_key(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(fx=None))
    with pytest.raises(DriveFormatError, match=r"missing required key\(s\) \['fx'\]"):
        load_drive(root)


def test_ill_typed_camera_key_names_line(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(width="wide"))
    with pytest.raises(DriveFormatError, match=r"camera.yaml:2: camera.yaml 'width'"):
        load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(height_m=-1))
    with pytest.raises(DriveFormatError, match=r":9: .*'height_m' must be > 0"):
        load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(dist="[1, 2]"))
    with pytest.raises(DriveFormatError, match="'dist' must be a list of 5 numbers"):
        load_drive(root)
    (root / "camera.yaml").write_text(camera_yaml(model="fisheye"))
    with pytest.raises(DriveFormatError, match="'model' must be 'pinhole'"):
        load_drive(root)


def test_integral_float_size_accepted(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml(width=f"{W}.0"))
    assert load_drive(root).camera.width == W
    (root / "camera.yaml").write_text(camera_yaml(width=f"{W}.5"))
    with pytest.raises(DriveFormatError, match="positive integer"):
        load_drive(root)


def test_unknown_camera_key(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text(camera_yaml() + "focal: 3\n")
    with pytest.raises(DriveFormatError, match=r":11: unknown key\(s\) \['focal'\]"):
        load_drive(root)


def test_bad_yaml_syntax(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "camera.yaml").write_text("width: [64\nheight: 48\n")
    with pytest.raises(DriveFormatError, match="not valid YAML"):
        load_drive(root)


# --------------------------------------------------------------------------- frames


def test_non_increasing_frame_timestamps(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    lines = (root / "frames.csv").read_text().splitlines()
    lines[3] = lines[3].split(",")[0] + ",0.1"  # same as line 3 (file line numbers are 1-based)
    (root / "frames.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DriveFormatError, match=r"frames.csv:4: frame timestamp 0.1 is not after"):
        load_drive(root)


def test_non_numeric_frame_timestamp(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    lines = (root / "frames.csv").read_text().splitlines()
    lines[2] = lines[2].split(",")[0] + ",abc"
    (root / "frames.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DriveFormatError, match=r"frames.csv:3: timestamp_s 'abc' is not a number"):
        load_drive(root)


def test_bad_frames_header(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    txt = (root / "frames.csv").read_text().replace("filename,timestamp_s", "file,time")
    (root / "frames.csv").write_text(txt)
    with pytest.raises(DriveFormatError, match=r"frames.csv:1: header"):
        load_drive(root)


def test_filenames_with_frames_prefix_are_accepted(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    txt = (root / "frames.csv").read_text().replace("\n0000", "\nframes/0000")
    (root / "frames.csv").write_text(txt)
    d = load_drive(root)
    assert len(d.frames) == 5 and d.frames[0].filename == "000000.png"
    assert any("'frames/'" in w for w in d.warnings)


def test_row_pointing_to_missing_image_is_skipped(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "frames" / "000002.png").unlink()
    d = load_drive(root)
    assert [f.filename for f in d.frames] == [
        "000000.png",
        "000001.png",
        "000003.png",
        "000004.png",
    ]
    assert [f.index for f in d.frames] == [0, 1, 2, 3]
    (s,) = d.skipped
    assert s.file == "frames.csv" and s.line == 4 and "does not exist" in s.reason
    assert any("missing" in w for w in d.warnings)


def test_all_images_missing_is_an_error(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", n=2)
    for p in (root / "frames").iterdir():
        p.unlink()
    with pytest.raises(DriveFormatError, match="empty drive"):
        load_drive(root)


def test_empty_drive(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", n=0, gps=None)
    with pytest.raises(DriveFormatError, match="empty drive"):
        load_drive(root)
    with pytest.raises(DriveFormatError, match="drive folder not found"):
        load_drive(tmp_path / "nope")
    (tmp_path / "e").mkdir()
    (tmp_path / "e" / "camera.yaml").write_text(camera_yaml())
    with pytest.raises(DriveFormatError, match="frames.csv not found"):
        load_drive(tmp_path / "e")


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_truncated_image_is_skipped_and_read_raises(tmp_path: Path, ext: str) -> None:
    root = make_drive(tmp_path / "d", ext=ext)
    p = root / "frames" / f"000002{ext}"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    d = load_drive(root)
    assert len(d.frames) == 4 and "000002" not in " ".join(f.filename for f in d.frames)
    (s,) = d.skipped
    assert s.file == f"frames/000002{ext}" and "truncated" in s.reason
    # The reader refuses the same file with FrameReadError (e.g. when check_images=False).
    d2 = load_drive(root, check_images=False)
    assert len(d2.frames) == 5
    with pytest.raises(FrameReadError, match="truncated"):
        read_image(d2.frames[2])
    with pytest.raises(FrameReadError):
        read_gray(d2.frames[2])


def test_garbage_image_is_skipped(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    (root / "frames" / "000001.png").write_bytes(b"not an image at all")
    (root / "frames" / "000003.png").write_bytes(b"")
    d = load_drive(root)
    assert len(d.frames) == 3
    reasons = {s.file: s.reason for s in d.skipped}
    assert "signature" in reasons["frames/000001.png"]
    assert "empty" in reasons["frames/000003.png"]


def test_corrupt_jpeg_body_with_valid_markers_is_skipped(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", ext=".jpg")
    p = root / "frames" / "000001.jpg"
    data = bytearray(p.read_bytes())
    # Keep SOI and EOI but destroy the headers: cv2 cannot decode it.
    data[2:200] = b"\x00" * 198
    p.write_bytes(bytes(data))
    d = load_drive(root)
    assert [s.file for s in d.skipped] == ["frames/000001.jpg"]


def test_image_size_mismatch_names_file(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    cv2.imwrite(str(root / "frames" / "000003.png"), np.zeros((H + 2, W, 3), np.uint8))
    with pytest.raises(DriveFormatError, match=r"000003.png: image is 64x50 px but camera.yaml"):
        load_drive(root)


def test_unlisted_images_warn(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    cv2.imwrite(str(root / "frames" / "zzz.png"), texture(1))
    d = load_drive(root)
    assert len(d.frames) == 5 and any("not listed" in w for w in d.warnings)


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


def _nmea(body: str) -> str:
    c = 0
    for ch in body:
        c ^= ord(ch)
    return f"${body}*{c:02X}"


def _ddmm(v: float, pos: str, neg: str, width: int) -> str:
    a = abs(v)
    d = math.floor(a)
    return f"{d:0{width}d}{(a - d) * 60:07.4f},{pos if v >= 0 else neg}"


def test_nmea_rmc_gga_checksum(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", t0=T0, gps=None)
    dt0 = datetime.fromtimestamp(T0, UTC)
    lines = []
    for k in range(4):
        t = dt0.timestamp() - 0.5 + 0.5 * k
        dt = datetime.fromtimestamp(t, UTC)
        hms = dt.strftime("%H%M%S") + f".{dt.microsecond // 10000:02d}"
        lat = _ddmm(LAT0 + 1e-5 * k, "N", "S", 2)
        lon = _ddmm(LON0, "E", "W", 3)
        date = dt.strftime("%d%m%y")
        lines.append(_nmea(f"GPRMC,{hms},A,{lat},{lon},10.0,90.0,{date},,"))
        lines.append(_nmea(f"GPGGA,{hms},{lat},{lon},1,08,0.9,{120 + k}.0,M,-34.0,M,,"))
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
    assert d.gps.hdop[0] == pytest.approx(0.9) and d.gps.alt_m[2] == pytest.approx(122.0)
    (s,) = [s for s in d.skipped if s.file == "gps.nmea"]
    assert s.line == 3 and "checksum" in s.reason


def test_nmea_without_rmc_is_an_error(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", gps=None)
    (root / "gps.nmea").write_text(
        _nmea("GPGGA,120000.00,4336.0000,N,07924.0000,W,1,08,0.9,120.0,M,-34.0,M,,") + "\n"
    )
    with pytest.raises(DriveFormatError, match="no valid \\$GPRMC"):
        load_drive(root)


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


# --------------------------------------------------------------------------- speed


def test_check_images_is_fast_on_many_frames(tmp_path: Path) -> None:
    """Not a timing assertion: checks that 200 JPEG frames load and are all validated."""
    d = load_drive(make_drive(tmp_path / "d", n=200, ext=".jpg"))
    assert len(d.frames) == 200 and not d.skipped


def test_gps_verbatim_duplicate_row_is_dropped_not_fatal(tmp_path: Path) -> None:
    rows = [f"0.0,{LAT0},{LON0}", f"0.5,{LAT0},{LON0}", f"0.5,{LAT0},{LON0}", f"1.0,{LAT0},{LON0}"]
    d = load_drive(make_drive(tmp_path / "d", gps_rows=rows))
    assert d.gps is not None and len(d.gps) == 3
    (s,) = [s for s in d.skipped if s.file == "gps.csv"]
    assert s.line == 4 and "duplicate" in s.reason


# --------------------------------------------------------------------------- distance along


def test_along_track_from_obd_else_gps_else_none(tmp_path: Path) -> None:
    """Frames at 10 Hz: OBD speed 5 m/s -> 0.5 m per frame; without OBD the GPS path (fixes
    1e-5 deg of latitude = 1.11 m apart every 0.5 s -> 0.222 m per frame); neither -> None."""
    from roadsurf.io.drive import along_track_m

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
