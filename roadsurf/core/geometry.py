"""Pure numpy geometry helpers, named target-from-source.

Frames (metres everywhere):
- **ENU** (map frame): x east, y north, z up, origin at a saved WGS84 reference point
  (``EnuReference``). All internal map work happens here.
- **Camera**: x right (vehicle right), y backward (image down = towards the vehicle's rear),
  z down along the optical axis. Pixels: u right, v down, origin at the top-left pixel centre.
- **Pose** ``world_from_cam`` is a 4x4 matrix T with X_world = T[:3,:3] @ X_cam + T[:3,3].
- **Heading** ``heading_deg`` is a compass bearing of the vehicle's forward direction, clockwise
  from north, in [0, 360). The dissertation's eq. 6.1 angle θ = atan2(-dx, dy) is
  counter-clockwise from north: heading = -θ.

WGS84 / UTM only appear at the edges (loading GPS, exporting), through pyproj.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from pyproj import CRS, Transformer


def check_shape(name: str, arr: np.ndarray, shape: tuple[int | None, ...]) -> np.ndarray:
    """Return ``arr`` as an ndarray after checking it matches ``shape`` (None = any size)."""
    a = np.asarray(arr)
    if a.ndim != len(shape) or any(
        s is not None and s != d for s, d in zip(shape, a.shape, strict=True)
    ):
        want = str(tuple("N" if s is None else s for s in shape)).replace("'", "")
        raise ValueError(f"{name}: expected shape {want}, got {a.shape}")
    return a


# --------------------------------------------------------------------------- WGS84 / ENU / UTM


@dataclass(frozen=True)
class EnuReference:
    """Origin of the local ENU map frame (WGS84 degrees, ellipsoidal metres)."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0

    def to_dict(self) -> dict[str, float]:
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "alt_m": self.alt_m}

    @classmethod
    def from_dict(cls, d: dict[str, float]) -> EnuReference:
        return cls(float(d["lat_deg"]), float(d["lon_deg"]), float(d.get("alt_m", 0.0)))


@lru_cache(maxsize=8)
def _ecef_from_lla_transformer() -> Transformer:
    return Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


def _enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Rows are the E, N, U unit vectors in ECEF at (lat, lon)."""
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, so, co = math.sin(la), math.cos(la), math.sin(lo), math.cos(lo)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def enu_from_lla(
    lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray | float, ref: EnuReference
) -> np.ndarray:
    """WGS84 (degrees, metres) -> local ENU (metres). Inputs broadcast to (N,); returns (N, 3)."""
    lat = np.atleast_1d(np.asarray(lat_deg, dtype=float))
    lon = np.atleast_1d(np.asarray(lon_deg, dtype=float))
    alt = np.broadcast_to(np.asarray(alt_m, dtype=float), lat.shape)
    tr = _ecef_from_lla_transformer()
    x, y, z = tr.transform(lon, lat, alt)
    x0, y0, z0 = tr.transform(ref.lon_deg, ref.lat_deg, ref.alt_m)
    d = np.stack([np.asarray(x) - x0, np.asarray(y) - y0, np.asarray(z) - z0], axis=-1)
    return d @ _enu_rotation(ref.lat_deg, ref.lon_deg).T


def lla_from_enu(enu_m: np.ndarray, ref: EnuReference) -> np.ndarray:
    """Local ENU (N, 3) metres -> WGS84 (N, 3) as columns lat_deg, lon_deg, alt_m."""
    enu = check_shape("enu_m", np.atleast_2d(enu_m), (None, 3)).astype(float)
    tr = _ecef_from_lla_transformer()
    x0, y0, z0 = tr.transform(ref.lon_deg, ref.lat_deg, ref.alt_m)
    ecef = enu @ _enu_rotation(ref.lat_deg, ref.lon_deg) + np.array([x0, y0, z0])
    lon, lat, alt = tr.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2], direction="INVERSE")
    return np.stack([np.asarray(lat), np.asarray(lon), np.asarray(alt)], axis=-1)


def utm_zone_number(lon_deg: float) -> int:
    """The plain 6° UTM zone (1-60) of a longitude (degrees), without the grid's exceptions."""
    return int((lon_deg + 180.0) // 6.0) % 60 + 1


def utm_epsg_for(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS84 UTM zone holding (lat, lon), e.g. 32617 for 17N, with the grid's
    two exceptions: south-west Norway (56-64°N, 3-12°E) is in zone 32, and Svalbard (72-84°N,
    0-42°E) in zones 31, 33, 35 and 37 only (the zones Norwegian agencies and MGRS use)."""
    zone = utm_zone_number(lon_deg)
    if 56.0 <= lat_deg < 64.0 and 3.0 <= lon_deg < 12.0:
        zone = 32
    elif 72.0 <= lat_deg < 84.0 and 0.0 <= lon_deg < 42.0:
        zone = 31 + 2 * int(min((lon_deg + 3.0) // 12.0, 3))
    return (32600 if lat_deg >= 0 else 32700) + zone


def utm_exception_key(lat_deg: float, lon_deg: float) -> str:
    """ "" where ``utm_epsg_for`` gives the plain 6° zone, else "utm:<EPSG>": the resume keys
    of outputs in the export CRS hold it, so runs made before the exceptions (Bergen in 31N)
    are redone in the zone now named, and every other run keeps its key."""
    plain = utm_zone_number(lon_deg) + (32600 if lat_deg >= 0 else 32700)
    epsg = utm_epsg_for(lat_deg, lon_deg)
    return "" if epsg == plain else f"utm:{epsg}"


@lru_cache(maxsize=16)
def _utm_transformer(epsg: int) -> Transformer:
    return Transformer.from_crs(CRS.from_epsg(4326), CRS.from_epsg(epsg), always_xy=True)


def utm_from_lla(lat_deg: np.ndarray, lon_deg: np.ndarray, epsg: int) -> np.ndarray:
    """WGS84 degrees -> UTM (N, 2) easting, northing in metres for the given EPSG zone."""
    e, n = _utm_transformer(epsg).transform(np.atleast_1d(lon_deg), np.atleast_1d(lat_deg))
    return np.stack([np.asarray(e, float), np.asarray(n, float)], axis=-1)


def lla_from_utm(easting_m: np.ndarray, northing_m: np.ndarray, epsg: int) -> np.ndarray:
    """UTM metres -> WGS84 (N, 2) columns lat_deg, lon_deg."""
    lon, lat = _utm_transformer(epsg).transform(
        np.atleast_1d(easting_m), np.atleast_1d(northing_m), direction="INVERSE"
    )
    return np.stack([np.asarray(lat, float), np.asarray(lon, float)], axis=-1)


@dataclass(frozen=True)
class ExportFrame:
    """ENU <-> UTM mapping used when exporting (the ENU frame is tiny; UTM is the GIS frame)."""

    ref: EnuReference
    epsg: int

    @property
    def crs(self) -> str:
        return f"EPSG:{self.epsg}"

    @classmethod
    def for_reference(cls, ref: EnuReference) -> ExportFrame:
        return cls(ref, utm_epsg_for(ref.lat_deg, ref.lon_deg))

    def utm_from_enu(self, enu_m: np.ndarray) -> np.ndarray:
        """(N, 3) ENU metres -> (N, 3) easting, northing, ellipsoidal height (metres; through
        ECEF, so a point far from the reference keeps its height: ENU up + the reference's
        altitude would drop by d² / 2R, 8 cm at 1 km)."""
        enu = check_shape("enu_m", np.atleast_2d(enu_m), (None, 3))
        lla = lla_from_enu(enu, self.ref)
        en = utm_from_lla(lla[:, 0], lla[:, 1], self.epsg)
        return np.column_stack([en, lla[:, 2]])

    def lonlat_from_enu(self, enu_m: np.ndarray) -> np.ndarray:
        """(N, 2|3) ENU metres -> (N, 2) lon, lat degrees (RFC 7946 axis order)."""
        enu = np.atleast_2d(np.asarray(enu_m, float))
        if enu.shape[1] == 2:
            enu = np.column_stack([enu, np.zeros(len(enu))])
        lla = lla_from_enu(enu, self.ref)
        return lla[:, [1, 0]]


# --------------------------------------------------------------------------- rotations / poses


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) -> (3, 3) cross-product matrix [v]x."""
    x, y, z = check_shape("v", np.asarray(v, float), (3,))
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation_b_from_a(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation R with R a = b for directions a, b (3,) (normalised here):
    about their common normal, no twist about either (Rodrigues). Identity when they coincide;
    a half turn about an axis normal to a when they are opposite."""
    a = check_shape("a", np.asarray(a, float), (3,)) / np.linalg.norm(a)
    b = check_shape("b", np.asarray(b, float), (3,)) / np.linalg.norm(b)
    c = float(a @ b)
    if c < -1.0 + 1e-12:  # opposite: a half turn about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = skew(np.cross(a, b))
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def rotation_from_euler_xyz(rx_rad: float, ry_rad: float, rz_rad: float) -> np.ndarray:
    """R = Rz @ Ry @ Rx (rotations about the camera x, y, z axes, radians)."""
    cx, sx, cy, sy, cz, sz = (
        math.cos(rx_rad),
        math.sin(rx_rad),
        math.cos(ry_rad),
        math.sin(ry_rad),
        math.cos(rz_rad),
        math.sin(rz_rad),
    )
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def vehicle_from_cam_rotation(pitch_deg: float, roll_deg: float, yaw_deg: float) -> np.ndarray:
    """(3, 3) R_vehicle_from_cam = Rz(yaw) Ry(roll) Rx(pitch) from mount angles (degrees).

    Vehicle frame = that of a nadir camera: x to the vehicle's right, y backward, z down into
    the road. pitch > 0 tilts the optical axis forward from nadir, roll > 0 tilts it to the
    right, yaw > 0 turns it clockwise seen from above; all zero is the nadir camera."""
    return rotation_from_euler_xyz(
        math.radians(pitch_deg), math.radians(roll_deg), math.radians(yaw_deg)
    )


def vehicle_from_flu(v_flu: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """(3,) a vector given as [forward, left, up] (ISO 8855 axes, as camera.yaml's
    gps_antenna_m) in the vehicle frame (a nadir camera's: x right, y backward, z down)."""
    f, left, u = (float(x) for x in check_shape("v_flu", np.asarray(v_flu, float), (3,)))
    return np.array([-left, -f, -u])


def mount_angles_deg(R_vehicle_from_cam: np.ndarray) -> tuple[float, float, float]:
    """(pitch, roll, yaw) degrees of a (3, 3) R_vehicle_from_cam (inverse of
    ``vehicle_from_cam_rotation``; roll within ±90°)."""
    R = check_shape("R_vehicle_from_cam", np.asarray(R_vehicle_from_cam, float), (3, 3))
    pitch = math.atan2(R[2, 1], R[2, 2])
    roll = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    yaw = math.atan2(R[1, 0], R[0, 0])
    return math.degrees(pitch), math.degrees(roll), math.degrees(yaw)


def up_in_cam(R_vehicle_from_cam: np.ndarray) -> np.ndarray:
    """(3,) unit 'up' (away from the road, vehicle −z) in camera coordinates of a level vehicle."""
    return np.asarray(R_vehicle_from_cam, float).T @ np.array([0.0, 0.0, -1.0])


def forward_in_cam(R_vehicle_from_cam: np.ndarray) -> np.ndarray:
    """(3,) unit driving direction (vehicle −y) in camera coordinates."""
    return np.asarray(R_vehicle_from_cam, float).T @ np.array([0.0, -1.0, 0.0])


def right_in_cam(R_vehicle_from_cam: np.ndarray) -> np.ndarray:
    """(3,) unit vehicle right (vehicle +x) in camera coordinates."""
    return np.asarray(R_vehicle_from_cam, float).T @ np.array([1.0, 0.0, 0.0])


def vehicle_from_up_forward(up_cam: np.ndarray, forward_cam: np.ndarray) -> np.ndarray:
    """(3, 3) R_vehicle_from_cam from 'up' and an approximate driving direction, both (3,) in
    camera coordinates: forward is made orthogonal to up (Gram-Schmidt)."""
    u = np.asarray(up_cam, float)
    u = u / np.linalg.norm(u)
    f = np.asarray(forward_cam, float) - u * float(np.dot(forward_cam, u))
    n = float(np.linalg.norm(f))
    if n < 1e-9:
        raise ValueError("forward direction is parallel to up")
    f = f / n
    right = np.cross(f, u)  # vehicle x (right) = forward x up for z-up, y-forward
    # rows: the vehicle axes (x right, y backward, z down) in camera coordinates
    return np.vstack([right, -f, -u])


def world_from_vehicle_rotation(heading_deg: float) -> np.ndarray:
    """Rotation whose columns are the camera axes (right, backward, down) in ENU for a level
    vehicle with compass ``heading_deg``. Returns (3, 3) world_from_cam for zero roll/pitch."""
    b = math.radians(heading_deg)
    fwd = np.array([math.sin(b), math.cos(b), 0.0])
    right = np.array([math.cos(b), -math.sin(b), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    return np.column_stack([right, -fwd, down])


def world_from_cam(
    heading_deg: float,
    roll_rad: float = 0.0,
    pitch_rad: float = 0.0,
    position_enu_m: np.ndarray | None = None,
) -> np.ndarray:
    """4x4 pose of a camera mounted looking down, given heading and small roll/pitch.

    Roll is a rotation about the camera y axis (backward), pitch about the camera x axis (right);
    both are applied in the camera frame before the heading.
    """
    T = np.eye(4)
    T[:3, :3] = world_from_vehicle_rotation(heading_deg) @ rotation_from_euler_xyz(
        pitch_rad, roll_rad, 0.0
    )
    if position_enu_m is not None:
        T[:3, 3] = check_shape("position_enu_m", np.asarray(position_enu_m, float), (3,))
    return T


def heading_deg_from_world_rotation(
    R_world_from_cam: np.ndarray, R_vehicle_from_cam: np.ndarray | None = None
) -> float:
    """Compass heading of the vehicle's forward direction, degrees in [0, 360). Without a mount
    rotation the camera is nadir and forward is the -camera y axis."""
    R = check_shape("R_world_from_cam", R_world_from_cam, (3, 3))
    fwd = -R[:, 1] if R_vehicle_from_cam is None else R @ forward_in_cam(R_vehicle_from_cam)
    return float(math.degrees(math.atan2(fwd[0], fwd[1])) % 360.0)


def heading_deg_from_displacement(d_east_m: np.ndarray, d_north_m: np.ndarray) -> np.ndarray:
    """Compass heading (degrees, [0, 360)) of successive-fix displacements (dissertation eq. 6.1)."""
    return np.degrees(np.arctan2(np.asarray(d_east_m, float), np.asarray(d_north_m, float))) % 360.0


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    T = check_shape("T", T, (4, 4))
    P = check_shape("pts", np.atleast_2d(pts), (None, 3))
    return P @ T[:3, :3].T + T[:3, 3]


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    T = check_shape("T", T, (4, 4))
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti
