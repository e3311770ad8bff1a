"""Tiny drives built in a test's tmp_path (shared by the drive-loader and benchmark tests)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

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
    frame_dt: float = 0.1,
) -> Path:
    """n frames every frame_dt s (10 Hz) from t0; GPS at 2 Hz covering the frames."""
    (root / "frames").mkdir(parents=True)
    (root / "camera.yaml").write_text(camera_yaml())
    rows = ["filename,timestamp_s"]
    for i in range(n):
        name = f"{i:06d}{ext}"
        cv2.imwrite(str(root / "frames" / name), texture(i))
        rows.append(f"{name},{t0 + frame_dt * i:.3f}")
    (root / "frames.csv").write_text("\n".join(rows) + "\n")
    if gps == "csv":
        if gps_rows is None:
            gps_rows = [
                f"{t0 + 0.5 * k - 0.5:.3f},{LAT0 + 1e-6 * k:.8f},{LON0:.8f},100.0,0.8"
                for k in range(int(n * 0.2) + 3)
            ]
        (root / "gps.csv").write_text("timestamp_s,lat,lon,alt_m,hdop\n" + "\n".join(gps_rows))
    return root


def moving_gps_rows(
    t_start: float, t_end: float, speed_mps: float, rate_hz: float = 2.0, hdop: float = 0.8
) -> list[str]:
    """gps.csv rows of a receiver driving north at speed_mps (1 deg of latitude = 111.2 km)."""
    n = round((t_end - t_start) * rate_hz) + 1
    return [
        f"{t_start + k / rate_hz:.3f},{LAT0 + speed_mps * k / rate_hz / 111_195.0:.9f},"
        f"{LON0:.9f},100.0,{hdop}"
        for k in range(n)
    ]


def nmea(body: str) -> str:
    """$body*checksum."""
    c = 0
    for ch in body:
        c ^= ord(ch)
    return f"${body}*{c:02X}"


def ddmm(v: float, pos: str, neg: str, width: int) -> str:
    """Signed degrees -> NMEA ddmm.mmmm,H (width: 2 for latitude, 3 for longitude)."""
    a = abs(v)
    d = int(a)
    return f"{d:0{width}d}{(a - d) * 60:07.4f},{pos if v >= 0 else neg}"


def nmea_lines(
    t0: float,
    n: int,
    dt: float = 0.5,
    geoid_sep: str = "-34.0",
    quality: int = 1,
    alt_step_m: float = 0.0,
    gst_offset_s: float | None = None,
) -> list[str]:
    """RMC + GGA per fix from t0 (UNIX s), moving north 1e-5 deg per fix; GGA fix ``quality``,
    altitude 120 m + k ``alt_step_m`` (mean sea level) with the given geoid separation (field
    11; "" for none); with ``gst_offset_s`` a GST (σ lat 0.03 m, σ lon 0.04 m) that long after
    each fix."""
    from datetime import UTC, datetime

    out = []
    for k in range(n):
        u = datetime.fromtimestamp(t0 + dt * k, UTC)
        hms = u.strftime("%H%M%S") + f".{u.microsecond // 10000:02d}"
        lat, lon = ddmm(LAT0 + 1e-5 * k, "N", "S", 2), ddmm(LON0, "E", "W", 3)
        alt = 120.0 + alt_step_m * k
        out.append(nmea(f"GPRMC,{hms},A,{lat},{lon},10.0,90.0,{u:%d%m%y},,"))
        out.append(nmea(f"GPGGA,{hms},{lat},{lon},{quality},08,0.9,{alt:.1f},M,{geoid_sep},M,,"))
        if gst_offset_s is not None:
            g = datetime.fromtimestamp(t0 + dt * k + gst_offset_s, UTC)
            ghms = g.strftime("%H%M%S") + f".{g.microsecond // 10000:02d}"
            # rms, semi-major, semi-minor, orientation, σ lat, σ lon, σ alt (m)
            out.append(nmea(f"GPGST,{ghms},0.006,0.023,0.020,273.6,0.030,0.040,0.05"))
    return out


def gpx_text(t0: float, n: int, dt: float = 0.5, ele: bool = True) -> str:
    """GPX 1.1 track of n points from t0 (UNIX s), moving north 1e-5 deg per point."""
    from datetime import UTC, datetime

    pts = []
    for k in range(n):
        iso = datetime.fromtimestamp(t0 + dt * k, UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
        e = f"<ele>{100 + k}</ele>" if ele else ""
        pts.append(
            f'<trkpt lat="{LAT0 + 1e-5 * k:.8f}" lon="{LON0}">{e}<time>{iso}</time>'
            f"<hdop>1.2</hdop></trkpt>"
        )
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<gpx version="1.1" '
        'xmlns="http://www.topografix.com/GPX/1/1">\n<trk><trkseg>\n'
        + "\n".join(pts)
        + "\n</trkseg></trk></gpx>\n"
    )
