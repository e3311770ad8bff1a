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
