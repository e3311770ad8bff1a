"""Data types of a loaded drive (frames, GPS track, OBD log, skipped items) and the distance
travelled along it. The format itself is described in ``roadsurf.io.drive`` and docs/formats.md."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.geometry import EnuReference, enu_from_lla
from roadsurf.io import drivefolder as df

FORMAT_HINT = "See docs/formats.md for the drive format."

# Plain words for every warning after which the run has no georeference (it must not read as success).
NO_GEOREF = "NO GEOREFERENCE: the map will be in a local frame with no lon/lat outputs"

# Vertical datum of ``GpsTrack.alt_m`` (outputs name it).
ALT_ELLIPSOIDAL = "WGS84 ellipsoidal height"
ALT_MSL = "mean sea level (geoid unknown)"
ALT_GPX_ELE = "GPX ele (orthometric, geoid per the device)"
ALT_NONE = "none (the log has no altitude)"


@dataclass(frozen=True)
class Frame:
    """One valid image of the drive."""

    index: int  # position among the drive's valid frames, in capture order
    filename: str  # as written in frames.csv (relative to DRIVE/frames/)
    path: Path
    timestamp_s: float


@dataclass
class GpsTrack:
    """GPS fixes of the antenna (camera.yaml gps_antenna_m from the camera centre; at it when
    not given), WGS84. All arrays (N,), sorted by time."""

    timestamp_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray  # NaN where the log has no altitude; vertical datum: ``alt_datum``
    hdop: np.ndarray  # NaN where the log has no HDOP
    source: str = df.GPS_CSV  # file it came from
    alt_datum: str = ALT_ELLIPSOIDAL  # one of the ALT_* names above
    # the receiver's own horizontal σ per axis (m): gps.csv 'sigma_m', NMEA GST; NaN where the
    # log states none (empty: nowhere)
    sigma_m: np.ndarray = field(default_factory=lambda: np.empty(0))
    # NMEA GGA fix quality (gps.csv 'fix_quality'): 4 RTK fixed, 5 RTK float, 1 GPS, 2 DGPS...;
    # 0 where the log gives none (empty: nowhere)
    quality: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))

    def __post_init__(self) -> None:
        n = len(self.timestamp_s)
        if len(self.sigma_m) != n:
            self.sigma_m = np.full(n, np.nan)
        if len(self.quality) != n:
            self.quality = np.zeros(n, np.int64)

    def __len__(self) -> int:
        return int(self.timestamp_s.shape[0])

    @property
    def states_accuracy(self) -> bool:
        """Whether any fix carries a stated σ or an RTK fix quality (4 or 5): what
        ``mapping.gps_sigma_from_log`` weighs by."""
        return bool(np.isfinite(self.sigma_m).any() or np.isin(self.quality, (4, 5)).any())


@dataclass
class ObdLog:
    """Vehicle speed from OBD-II. Arrays (N,)."""

    timestamp_s: np.ndarray
    speed_mps: np.ndarray


@dataclass(frozen=True)
class Skipped:
    """Something the loader or a stage dropped, and why (goes to report.json)."""

    file: str
    line: int | None
    reason: str


@dataclass
class Drive:
    root: Path
    camera: Camera
    frames: list[Frame]
    gps: GpsTrack | None
    obd: ObdLog | None
    skipped: list[Skipped] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def truth_dir(self) -> Path | None:
        p = self.root / df.TRUTH_DIR
        return p if p.is_dir() else None


def along_track_m(drive: Drive) -> np.ndarray | None:
    """(N,) distance travelled (m) at each frame's timestamp, from 0 at the first frame.

    From the OBD speed (integrated, trapezoids) when the drive has at least two speed samples,
    else from the path length of the GPS fixes. Times outside the log are extrapolated at the
    speed of its end. None when the drive has neither (a caller then counts frames instead).
    GPS noise lengthens the path (about +3 % for σ 1 m fixes 6 m apart); the estimate is meant
    for spacing work along the drive, not for measurements.
    """
    t_frames = np.array([f.timestamp_s for f in drive.frames], dtype=float)
    if len(t_frames) == 0:
        return None
    t: np.ndarray | None = None
    s: np.ndarray | None = None
    if drive.obd is not None and len(drive.obd.timestamp_s) >= 2:
        o = np.argsort(drive.obd.timestamp_s, kind="stable")
        t = np.asarray(drive.obd.timestamp_s, float)[o]
        v = np.abs(np.asarray(drive.obd.speed_mps, float)[o])
        s = np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))]
    elif drive.gps is not None and len(drive.gps) >= 2:
        g = drive.gps
        ref = EnuReference(float(g.lat_deg[0]), float(g.lon_deg[0]), 0.0)
        xy = enu_from_lla(g.lat_deg, g.lon_deg, 0.0, ref)[:, :2]
        t = np.asarray(g.timestamp_s, float)
        s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    if t is None or s is None or not np.all(np.isfinite(s)) or t[-1] <= t[0]:
        return None
    out = np.interp(t_frames, t, s)
    v0 = (s[1] - s[0]) / max(t[1] - t[0], 1e-9)
    v1 = (s[-1] - s[-2]) / max(t[-1] - t[-2], 1e-9)
    out = np.where(t_frames < t[0], s[0] - v0 * (t[0] - t_frames), out)
    out = np.where(t_frames > t[-1], s[-1] + v1 * (t_frames - t[-1]), out)
    return out - out[0]


def log_overlap(t_log: np.ndarray, frames: list[Frame]) -> tuple[float, float | None]:
    """A time-stamped log (GPS, OBD; (N,) s, increasing) against the frames' time span: (its
    median interval (s; 1 s for a single row), the share of the frames' span it covers, or None
    when it misses the span by more than one interval: a log on another clock)."""
    t = np.asarray(t_log, float)
    t0, t1 = frames[0].timestamp_s, frames[-1].timestamp_s
    slack = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    if t[-1] < t0 - slack or t[0] > t1 + slack:
        return slack, None
    return slack, (min(t1, t[-1]) - max(t0, t[0])) / (t1 - t0) if t1 > t0 else 1.0


def disjoint_text(t_log: np.ndarray, frames: list[Frame]) -> str:
    """'times [a, b] s do not overlap the frame times [c, d] s (offset about x s)' for a log
    ``log_overlap`` found on another clock (the warnings name the log and what follows)."""
    t0, t1 = frames[0].timestamp_s, frames[-1].timestamp_s
    a, b = float(t_log[0]), float(t_log[-1])
    return (
        f"times [{a:.3f}, {b:.3f}] s do not overlap the frame times [{t0:.3f}, {t1:.3f}] s "
        f"(offset about {a - t0:+.1f} s)"
    )
