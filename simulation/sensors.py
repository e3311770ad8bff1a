"""Sensor models: image formation (exposure, vignetting, motion blur, noise, 8-bit encoding),
GPS (lower rate, white noise, slow random-walk bias, dropouts) and OBD speed."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from roadsurf.core.geometry import vehicle_from_flu
from roadsurf.simulation.config import SimConfig
from roadsurf.simulation.route import Pose
from roadsurf.simulation.world import World

# GPS profiles: rate (Hz), white noise σ per horizontal axis (m), bias std after 60 s (m), HDOP.
GPS_PROFILES = {
    "rtk": {"rate_hz": 5.0, "sigma_m": 0.02, "bias_m": 0.01, "hdop": 0.7},
    "consumer": {"rate_hz": 1.0, "sigma_m": 1.0, "bias_m": 1.5, "hdop": 1.6},
}


def gps_params(cfg: SimConfig) -> dict[str, float]:
    p = dict(GPS_PROFILES[cfg.gps_profile])
    if cfg.gps_rate_hz is not None:
        p["rate_hz"] = cfg.gps_rate_hz
    if cfg.gps_sigma_m is not None:
        p["sigma_m"] = cfg.gps_sigma_m
    if cfg.gps_bias_m is not None:
        p["bias_m"] = cfg.gps_bias_m
    return p


def form_image(
    radiance: np.ndarray, cfg: SimConfig, speed_mps: float, gain: float, rng: np.random.Generator
) -> np.ndarray:
    """Linear radiance (H, W, 3) -> uint8 RGB (H, W, 3) or grey (H, W) as the sensor writes it."""
    h, w = radiance.shape[:2]
    img = radiance * np.float32(255.0 * 0.95 * cfg.exposure * gain)
    if cfg.vignetting > 0:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        img *= (1.0 - cfg.vignetting * r2)[..., None]
    if cfg.mounted:
        img = _motion_blur_tilted(img, cfg, speed_mps)
        blur_px = 0.0
    else:  # motion blur along the image vertical (the direction of travel)
        blur_px = speed_mps * cfg.exposure_time_s * cfg.fx / cfg.camera_height_m
    if cfg.motion_blur and blur_px > 0.3:
        n = int(math.ceil(blur_px)) | 1
        k = np.zeros((n, 1), np.float32)
        centre = (n - 1) / 2
        for i in range(n):
            k[i, 0] = np.clip(blur_px / 2 + 0.5 - abs(i - centre), 0.0, 1.0)
        k /= k.sum()
        img = cv2.filter2D(img, -1, k, borderType=cv2.BORDER_REFLECT)
    sd = np.sqrt(cfg.noise_sigma**2 + cfg.shot_noise**2 * np.clip(img, 0, None))
    img = img + sd * rng.standard_normal(img.shape, dtype=np.float32)
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if cfg.greyscale:
        out = cv2.cvtColor(out, cv2.COLOR_RGB2GRAY)
    return out


@lru_cache(maxsize=4)
def _flow_px_per_m(cfg: SimConfig) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) image motion u, v (px) per metre the vehicle drives, for a level vehicle over a
    flat road at ``camera_height_m``: a tilted view's near rows move fast, its far rows slowly
    (ideal pinhole flow; the lens distortion's share is left out)."""
    cam = cfg.camera()
    vv, uu = np.mgrid[0 : cfg.height, 0 : cfg.width].astype(np.float64)
    n = cam.normalised_from_raw_px(np.column_stack([uu.ravel(), vv.ravel()]))
    x, y = n[:, 0], n[:, 1]
    R = cfg.vehicle_from_cam()
    t = cfg.camera_height_m / (R[2, 0] * x + R[2, 1] * y + R[2, 2])  # z-depth on the road
    V = R[1]  # the road moves backward (vehicle +y) past the camera, in camera axes
    du = cam.fx * (V[0] - x * V[2]) / t
    dv = cam.fy * (V[1] - y * V[2]) / t
    shape = (cfg.height, cfg.width)
    return du.reshape(shape).astype(np.float32), dv.reshape(shape).astype(np.float32)


def _motion_blur_tilted(img: np.ndarray, cfg: SimConfig, speed_mps: float) -> np.ndarray:
    """Motion blur of a tilted view: each pixel averaged along its own image motion during
    the exposure (the flow varies over the image), sampled at most 1 px apart."""
    du, dv = _flow_px_per_m(cfg)
    travel = np.float32(speed_mps * cfg.exposure_time_s)
    longest = float(travel * np.sqrt(du * du + dv * dv).max())
    if not cfg.motion_blur or longest <= 0.3:
        return img
    h, w = img.shape[:2]
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
    out = np.zeros_like(img)
    offsets = np.linspace(-0.5, 0.5, int(math.ceil(longest)) | 1, dtype=np.float32)
    for s in offsets:
        out += cv2.remap(
            img,
            uu + s * travel * du,
            vv + s * travel * dv,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT,
        )
    return out / np.float32(len(offsets))


def encode_image(img: np.ndarray, cfg: SimConfig) -> bytes:
    """uint8 RGB or grey -> JPEG/PNG bytes (deterministic)."""
    bgr = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if cfg.image_format == "jpg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)])
    else:
        ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise RuntimeError("OpenCV failed to encode a frame")
    return buf.tobytes()


@dataclass
class GpsLog:
    timestamp_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    hdop: np.ndarray
    dropped: list[tuple[float, float]]  # outage intervals (s)


def simulate_gps(world: World, rng: np.random.Generator) -> GpsLog:
    """GPS fixes of the antenna (the camera centre + ``gps_antenna_m`` on the vehicle's pose):
    truth + random-walk bias + white noise, with outages."""
    cfg = world.cfg
    p = gps_params(cfg)
    tr = world.traj
    period = 1.0 / p["rate_hz"]
    t = np.arange(tr.t[0] + 0.1, tr.t[-1] - 0.05, period)
    arm = vehicle_from_flu(cfg.gps_antenna_m)
    pos = np.array([_antenna(world.pose(float(ti)), arm, world) for ti in t])
    n = len(t)
    q = p["bias_m"] / math.sqrt(60.0)  # random-walk intensity (m / sqrt(s))
    bias = rng.normal(0, p["bias_m"] / 2, 3) + np.cumsum(
        rng.normal(0, q * math.sqrt(period), (n, 3)), axis=0
    )
    noise = rng.normal(0, p["sigma_m"], (n, 3))
    meas = pos + bias + noise * np.array([1.0, 1.0, 1.5])
    keep = np.ones(n, bool)
    dropped: list[tuple[float, float]] = []
    span = (world.frame_times[0], world.frame_times[-1])
    for _ in range(cfg.gps_dropouts):
        t0 = float(rng.uniform(span[0], max(span[0], span[1] - cfg.gps_dropout_s)))
        dropped.append((t0, t0 + cfg.gps_dropout_s))
        keep &= ~((t >= t0) & (t < t0 + cfg.gps_dropout_s))
    if keep.sum() < 2:  # always leave a usable log
        keep[[0, -1]] = True
    lla_e = meas[keep, 0] + world.origin_e_m
    lla_n = meas[keep, 1] + world.origin_n_m
    from roadsurf.core.geometry import lla_from_utm

    lla = lla_from_utm(lla_e, lla_n, world.epsg)
    hdop = np.round(p["hdop"] * (1 + 0.15 * np.abs(rng.standard_normal(int(keep.sum())))), 1)
    return GpsLog(
        timestamp_s=np.round(t[keep], 3),
        lat_deg=np.round(lla[:, 0], 9),
        lon_deg=np.round(lla[:, 1], 9),
        alt_m=np.round(meas[keep, 2] + cfg.origin_alt_m, 3),
        hdop=hdop,
        dropped=dropped,
    )


def _antenna(pose: Pose, arm: np.ndarray, world: World) -> np.ndarray:
    """(3,) the antenna at ``arm`` (the nadir camera's axes, m) on the vehicle's ``pose``."""
    if not arm.any():
        return np.asarray(pose.C, float)
    R_world_from_vehicle = pose.R @ world.cfg.vehicle_from_cam().T  # identity mount: nadir
    return np.asarray(pose.C, float) + R_world_from_vehicle @ arm


def simulate_obd(world: World, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """OBD-II speed: true speed + small noise, quantised like PID 0x0D (km/h)."""
    cfg = world.cfg
    tr = world.traj
    t = np.arange(tr.t[0] + 0.05, tr.t[-1], 1.0 / cfg.obd_rate_hz)
    v = np.interp(t, tr.t, tr.speed) + rng.normal(0, 0.03, len(t))
    if cfg.obd_quant_kmh > 0:
        q = cfg.obd_quant_kmh / 3.6
        v = np.round(v / q) * q
    return np.round(t, 3), np.round(np.clip(v, 0, None), 4)


def time_offset_s(cfg: SimConfig) -> float:
    """Offset added to every written timestamp: 0 with gps.csv (seconds since the recording
    started), the UNIX time of ``start_utc`` with GPX/NMEA logs (which carry UTC times)."""
    if cfg.gps_format == "csv":
        return 0.0
    from datetime import datetime

    return datetime.fromisoformat(cfg.start_utc).timestamp()


def _utc(t_unix: float):
    from datetime import UTC, datetime

    return datetime.fromtimestamp(round(t_unix, 3), tz=UTC)


def gpx_text(gps: GpsLog, offset_s: float) -> str:
    """GPX 1.1 track of the fixes (times ISO 8601 UTC with milliseconds)."""
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<gpx version="1.1" creator="roadsurf simulate" xmlns="http://www.topografix.com/GPX/1/1">',
        "<trk><name>roadsurf simulated drive</name><trkseg>",
    ]
    for t, la, lo, al, hd in zip(
        gps.timestamp_s, gps.lat_deg, gps.lon_deg, gps.alt_m, gps.hdop, strict=True
    ):
        iso = _utc(float(t) + offset_s).isoformat(timespec="milliseconds").replace("+00:00", "Z")
        lines.append(
            f'<trkpt lat="{la:.9f}" lon="{lo:.9f}"><ele>{al:.3f}</ele><time>{iso}</time>'
            f"<hdop>{hd:.1f}</hdop></trkpt>"
        )
    lines += ["</trkseg></trk>", "</gpx>", ""]
    return "\n".join(lines)


def _nmea(body: str) -> str:
    cs = 0
    for ch in body:
        cs ^= ord(ch)
    return f"${body}*{cs:02X}"


def _ddmm(value: float, deg_digits: int, pos: str, neg: str) -> tuple[str, str]:
    a = abs(value)
    d = int(a)
    m = (a - d) * 60.0
    return f"{d:0{deg_digits}d}{m:010.7f}", pos if value >= 0 else neg


def nmea_text(gps: GpsLog, offset_s: float, quality: int) -> str:
    """$GPRMC + $GPGGA per fix. Altitude is the ellipsoidal height with a geoid separation of 0,
    so MSL + separation and MSL give the same number. Speed/course from successive fixes."""
    out = []
    n = len(gps.timestamp_s)
    for i in range(n):
        t = float(gps.timestamp_s[i]) + offset_s
        u = _utc(t)
        hms = f"{u:%H%M%S}.{u.microsecond // 10000:02d}"
        lat, ns = _ddmm(float(gps.lat_deg[i]), 2, "N", "S")
        lon, ew = _ddmm(float(gps.lon_deg[i]), 3, "E", "W")
        j0, j1 = max(0, i - 1), min(n - 1, i + 1)
        if j1 > j0:
            dlat = (gps.lat_deg[j1] - gps.lat_deg[j0]) * 111_320.0
            dlon = (
                (gps.lon_deg[j1] - gps.lon_deg[j0]) * 111_320.0 * np.cos(np.radians(gps.lat_deg[i]))
            )
            dt = float(gps.timestamp_s[j1] - gps.timestamp_s[j0])
            knots = float(np.hypot(dlat, dlon)) / dt * 3600 / 1852
            course = float(np.degrees(np.arctan2(dlon, dlat)) % 360)
        else:
            knots, course = 0.0, 0.0
        out.append(
            _nmea(f"GPRMC,{hms},A,{lat},{ns},{lon},{ew},{knots:.2f},{course:.1f},{u:%d%m%y},,,A")
        )
        out.append(
            _nmea(
                f"GPGGA,{hms},{lat},{ns},{lon},{ew},{quality},12,{gps.hdop[i]:.1f},"
                f"{gps.alt_m[i]:.3f},M,0.0,M,,"
            )
        )
    return "\r\n".join(out) + "\r\n"
