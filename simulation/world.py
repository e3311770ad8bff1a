"""The simulated world: a gently curved route, the camera's continuous trajectory, and a road
surface (height + appearance) with defects and depth-less distractors.

Coordinates: local metric x (east), y (north), z (up), metres, relative to a UTM origin
(``World.origin_e_m``, ``World.origin_n_m``, ``cfg.origin_alt_m``) in the scenario's UTM CRS. The
world is a pure function of (config, seed): any window of it can be evaluated on demand
(``World.evaluate``), so frames render local patches and the truth raster is written block by
block, and memory scales with the road corridor, never with the bounding box of the route.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from roadsurf.core.geometry import lla_from_utm, utm_epsg_for, utm_from_lla, world_from_cam
from roadsurf.simulation.config import SimConfig
from roadsurf.simulation.noise import fractal_noise, value_noise
from roadsurf.simulation.shapes import Blob, Polyline, Rect
from roadsurf.simulation.texture import TextureField

log = logging.getLogger(__name__)

T_START_S = 2.0  # time stamp of the first frame (s); the logs start earlier, all stamps > 0
T_PAD_S = 1.5  # trajectory (and GPS/OBD logs) extend this long before and after the frames (s)


# --------------------------------------------------------------------------- route


@dataclass
class Route:
    """Centreline sampled every ``ds`` metres of arc length; heading is grid compass (rad)."""

    s: np.ndarray  # (M,) arc length (m)
    xy: np.ndarray  # (M, 2) local x, y (m)
    heading: np.ndarray  # (M,) grid heading, clockwise from grid north (rad)

    @classmethod
    def make(
        cls, length_m: float, heading0: float, amp: float, wavelength: float, phase: float
    ) -> Route:
        ds = 0.05
        s = np.arange(0.0, length_m + ds, ds)
        hd = heading0 + amp * np.sin(2 * np.pi * s / wavelength + phase)
        dx = np.sin(hd) * ds
        dy = np.cos(hd) * ds
        xy = np.column_stack(
            [
                np.concatenate([[0.0], np.cumsum(0.5 * (dx[1:] + dx[:-1]))]),
                np.concatenate([[0.0], np.cumsum(0.5 * (dy[1:] + dy[:-1]))]),
            ]
        )
        return cls(s, xy, hd)

    def heading_at(self, s: np.ndarray) -> np.ndarray:
        return np.interp(s, self.s, self.heading)

    def point(self, s: np.ndarray, lateral: np.ndarray) -> np.ndarray:
        """(N, 2) local x, y of arc length ``s`` and lateral offset (m, + = right of travel)."""
        s = np.atleast_1d(np.asarray(s, float))
        lat = np.broadcast_to(np.asarray(lateral, float), s.shape)
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        h = self.heading_at(s)
        return np.column_stack([x + lat * np.cos(h), y - lat * np.sin(h)])


# --------------------------------------------------------------------------- defects / distractors


@dataclass(frozen=True)
class Pothole:
    shape: Blob
    depth_m: float  # nominal depth D at the centre (m)
    power: float  # profile exponent: depth ∝ 1 - ρ^power (larger = flatter bottom, steeper wall)
    tilt: tuple[float, float]  # relative bottom tilt along x, y
    rough_m: float  # amplitude of the bottom roughness (m)
    darken: float  # albedo factor inside (< 1 darker)
    seed: int

    ragged: float = 0.05  # relative amplitude of the broken, ragged rim (fraction of ρ)

    def rho(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Normalised radius with a ragged rim: ρ (1 + ragged n(x, y)), n ~ clipped noise."""
        rho, _ = self.shape.rho_and_r(x, y)
        n = np.clip(value_noise(x, y, 0.02, self.seed + 17), -3.0, 3.0)
        return rho * (1.0 + self.ragged * n)

    def bbox(self, pad: float = 0.0) -> tuple[float, float, float, float]:
        return self.shape.bbox(pad + self.shape.r_max * (1.0 / (1.0 - 3 * self.ragged) - 1.0))

    def depth(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        rho = self.rho(x, y)
        prof = np.clip(1.0 - rho**self.power, 0.0, None)
        r = self.shape.radius
        lin = 1.0 + self.tilt[0] * (x - self.shape.cx) / r + self.tilt[1] * (y - self.shape.cy) / r
        rough = self.rough_m * fractal_noise(x, y, (0.015, 0.005), (1.0, 0.6), self.seed)
        d = self.depth_m * prof * lin + rough * np.sqrt(prof)
        return np.where(rho < 1.0, np.clip(d, 0.0, None), 0.0)


@dataclass(frozen=True)
class Trough:
    """A groove along a polyline: crack (narrow) or rut (wide, tapered ends)."""

    kind: str  # "crack" | "rut"
    line: Polyline
    depth_m: float  # depth at the centre line (m)
    taper_m: float  # length of the depth ramp at each end (m); 0 for cracks

    def depth(self, x: np.ndarray, y: np.ndarray, window=None) -> np.ndarray:
        d, along = self.line.distance(x, y, window)
        q = np.clip(2.0 * d / self.line.width, 0.0, 1.0)
        if self.kind == "crack":
            prof = 1.0 - q**2
        else:
            prof = (1.0 - q**2) ** 2
        if self.taper_m > 0:
            L = self.line.length
            ramp = np.clip(np.minimum(along, L - along) / self.taper_m, 0.0, 1.0)
            prof = prof * ramp * ramp * (3 - 2 * ramp)
        return self.depth_m * prof

    def dist(self, x: np.ndarray, y: np.ndarray, window=None) -> np.ndarray:
        return self.line.distance(x, y, window)[0]


@dataclass(frozen=True)
class Distractor:
    kind: str  # "lane_marking" | "shadow" | "oil_stain"
    shape: Blob | Rect
    strength: float  # paint coverage / shadow darkness / stain darkness (0..1)
    edge_m: float  # soft-edge width (m)


# --------------------------------------------------------------------------- trajectory


@dataclass
class Trajectory:
    """Camera motion sampled densely in time; poses are interpolated from it."""

    t: np.ndarray  # (T,) time (s)
    s: np.ndarray  # (T,) arc length along the route (m)
    speed: np.ndarray  # (T,) speed (m/s)
    lateral: np.ndarray  # (T,) lateral offset from the route centreline (m)
    dh: np.ndarray  # (T,) camera height deviation δ_h (m)
    roll: np.ndarray  # (T,) roll about camera y (rad)
    pitch: np.ndarray  # (T,) pitch about camera x (rad)
    yaw: np.ndarray  # (T,) yaw deviation from the road heading (rad)


@dataclass
class Pose:
    t: float
    C: np.ndarray  # (3,) camera centre, local x, y, z (m)
    R: np.ndarray  # (3, 3) world (grid E, N, U) from camera
    heading_deg: float  # grid heading (deg)
    roll_rad: float
    pitch_rad: float


# --------------------------------------------------------------------------- world


@dataclass
class World:
    cfg: SimConfig
    seed: int
    n_frames: int
    epsg: int
    origin_e_m: float
    origin_n_m: float
    route: Route
    traj: Trajectory
    frame_times: np.ndarray
    potholes: list[Pothole] = field(default_factory=list)
    troughs: list[Trough] = field(default_factory=list)
    distractors: list[Distractor] = field(default_factory=list)
    texture: TextureField | None = None
    base_waves: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    render_gsd_m: float = 0.001
    _relief: dict = field(default_factory=dict, repr=False)  # pothole index -> relief shadow

    # ---- derived helpers
    @property
    def crs(self) -> str:
        return f"EPSG:{self.epsg}"

    def lonlat_from_local(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) local x, y -> (N, 2) lon, lat (degrees)."""
        xy = np.atleast_2d(xy)
        lla = lla_from_utm(xy[:, 0] + self.origin_e_m, xy[:, 1] + self.origin_n_m, self.epsg)
        return lla[:, [1, 0]]

    def base(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Smooth road surface z (m, local): grade + cross slope + long-wave undulation."""
        c = self.cfg
        h0 = float(self.route.heading[0])
        along = x * math.sin(h0) + y * math.cos(h0)
        across = x * math.cos(h0) - y * math.sin(h0)
        z = c.grade * along - c.cross_slope * across
        for kx, ky, amp, ph in self.base_waves:
            z = z + amp * np.sin(kx * x + ky * y + ph)
        return z

    def base_grid(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """``base`` on the grid xs (cols) x ys (rows), computed separably: (rows, cols) float32."""
        c = self.cfg
        h0 = float(self.route.heading[0])
        gx = c.grade * math.sin(h0) - c.cross_slope * math.cos(h0)
        gy = c.grade * math.cos(h0) + c.cross_slope * math.sin(h0)
        z = (ys * gy)[:, None] + (xs * gx)[None, :]
        for kx, ky, amp, ph in self.base_waves:
            a, b = kx * xs + ph, ky * ys
            # sin(a + b) = sin a cos b + cos a sin b
            z += amp * (
                np.cos(b)[:, None] * np.sin(a)[None, :] + np.sin(b)[:, None] * np.cos(a)[None, :]
            )
        return z.astype(np.float32)

    def pose(self, t: float) -> Pose:
        tr, c = self.traj, self.cfg
        s = float(np.interp(t, tr.t, tr.s))
        lat = float(np.interp(t, tr.t, tr.lateral))
        xy = self.route.point(np.array([s]), np.array([lat]))[0]
        z = float(self.base(np.array(xy[0]), np.array(xy[1])))
        z += c.camera_height_m + float(np.interp(t, tr.t, tr.dh))
        hd = math.degrees(float(self.route.heading_at(np.array([s]))[0]))
        hd += math.degrees(float(np.interp(t, tr.t, tr.yaw)))
        roll = float(np.interp(t, tr.t, tr.roll))
        pitch = float(np.interp(t, tr.t, tr.pitch))
        T = world_from_cam(hd % 360.0, roll, pitch, np.array([xy[0], xy[1], z]))
        return Pose(t, T[:3, 3].copy(), T[:3, :3].copy(), hd % 360.0, roll, pitch)

    def camera_path_lateral(self, s: np.ndarray) -> np.ndarray:
        """Lateral offset of the camera where it passes arc length s (m)."""
        return np.interp(s, self.traj.s, self.traj.lateral)

    # ---- cast shadows of the relief (pothole rims onto their floor)
    def _relief_shadow_window(
        self, p: Pothole, x0: float, y_top: float, gsd: float, shape: tuple[int, int]
    ) -> np.ndarray | None:
        """Sun shadow cast by pothole ``p``'s own walls, for the grid window starting at
        (x0, y_top) (pixel-centre lattice (k + 0.5) gsd); None when the sun is near zenith."""
        c = self.cfg
        if c.sun_elevation_deg >= 85.0 or c.ambient >= 1.0:
            return None
        key = (self.potholes.index(p), round(gsd, 9))
        if key not in self._relief:
            self._relief[key] = self._relief_shadow(p, gsd)
        k0, m0, mask = self._relief[key]
        kc = int(round(x0 / gsd - 0.5)) + np.arange(shape[1]) - k0
        mr = int(round(-y_top / gsd - 0.5)) + np.arange(shape[0]) - m0
        okc = (kc >= 0) & (kc < mask.shape[1])
        okr = (mr >= 0) & (mr < mask.shape[0])
        out = np.zeros(shape, np.float32)
        out[np.ix_(okr, okc)] = mask[np.ix_(mr[okr], kc[okc])]
        return out

    def _relief_shadow(self, p: Pothole, gsd: float) -> tuple[int, int, np.ndarray]:
        """Shadow mask of a pothole on the global render lattice: march from each point towards
        the sun and test whether the pothole's walls rise above the ray (soft-edged 0..1)."""
        c = self.cfg
        bx0, by0, bx1, by1 = p.bbox(0.01)
        k0, k1 = int(math.floor(bx0 / gsd)), int(math.ceil(bx1 / gsd))
        m0, m1 = int(math.floor(-by1 / gsd)), int(math.ceil(-by0 / gsd))
        xs = (np.arange(k0, k1) + 0.5) * gsd
        ys = -(np.arange(m0, m1) + 0.5) * gsd
        X, Y = np.meshgrid(xs, ys)
        h = -p.depth(X, Y).astype(np.float32)
        az, el = math.radians(c.sun_azimuth_deg), math.radians(c.sun_elevation_deg)
        reach = float(-h.min()) / math.tan(el)
        step = 1.5 * gsd
        n = min(160, int(math.ceil(reach / step)) + 1)
        cols, rows = np.meshgrid(
            np.arange(k1 - k0, dtype=np.float32), np.arange(m1 - m0, dtype=np.float32)
        )
        dc, dr = math.sin(az) * step / gsd, -math.cos(az) * step / gsd
        lit_margin = np.float32(1e-4)
        shadow = np.zeros(h.shape, bool)
        for j in range(1, n + 1):
            hs = cv2.remap(
                h, cols + np.float32(j * dc), rows + np.float32(j * dr), cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT, borderValue=0.0,
            )  # fmt: skip
            shadow |= hs > h + np.float32(j * step * math.tan(el)) + lit_margin
        mask = cv2.GaussianBlur(shadow.astype(np.float32), (0, 0), 0.8)
        return k0, m0, mask

    # ---- evaluation on a north-up grid
    def evaluate(
        self, x0: float, y_top: float, gsd: float, rows: int, cols: int, appearance: bool = True
    ) -> dict[str, np.ndarray]:
        """Evaluate the world on a grid whose pixel (r, c) centre is
        (x0 + (c + 0.5) gsd, y_top - (r + 0.5) gsd) in local metres.

        Returns float32 (rows, cols) arrays 'height' (z, m), 'base' (smooth road z, m),
        'depth' (defect depth below the road, >= 0, m), 'uneven' (δ field, m); with
        ``appearance`` also 'rgb' (rows, cols, 3) albedo and 'shadow' (0..1, darkening of the
        direct light).
        """
        xs = x0 + (np.arange(cols) + 0.5) * gsd
        ys = y_top - (np.arange(rows) + 0.5) * gsd
        X, Y = np.meshgrid(xs, ys)
        c = self.cfg
        base = self.base_grid(xs, ys)
        uneven = np.float32(c.unevenness_m) * fractal_noise(
            X, Y, (0.006, 0.02), (1.0, 0.6), self.seed * 13 + 1
        )
        depth = np.zeros((rows, cols), np.float32)
        win = (x0, y_top - rows * gsd, x0 + cols * gsd, y_top)

        def sub(bb):
            c0 = max(0, int(math.floor((bb[0] - x0) / gsd)))
            c1 = min(cols, int(math.ceil((bb[2] - x0) / gsd)) + 1)
            r0 = max(0, int(math.floor((y_top - bb[3]) / gsd)))
            r1 = min(rows, int(math.ceil((y_top - bb[1]) / gsd)) + 1)
            if c0 >= c1 or r0 >= r1:
                return None
            return (slice(r0, r1), slice(c0, c1))

        pot_masks = []
        for p in self.potholes:
            sl = sub(p.bbox(0.01))
            if sl is None:
                continue
            d = p.depth(X[sl], Y[sl]).astype(np.float32)
            depth[sl] = np.maximum(depth[sl], d)
            pot_masks.append((p, sl))
        trough_d = []
        for tr in self.troughs:
            sl = sub(tr.line.bbox(0.01))
            if sl is None:
                continue
            d = tr.depth(X[sl], Y[sl], win).astype(np.float32)
            depth[sl] = np.maximum(depth[sl], d)
            trough_d.append((tr, sl))
        out = {
            "height": base + uneven - depth,
            "base": base,
            "depth": depth,
            "uneven": uneven,
        }
        if not appearance:
            return out

        if self.texture is None:
            raise ValueError("World.evaluate(appearance=True) needs World.texture")
        grey = self.texture.grey(x0, y_top, gsd, rows, cols)
        alb = 0.1 + 0.8 * grey
        alb *= 1.0 + 0.1 * value_noise(X, Y, 0.7, self.seed * 13 + 2)
        tint = np.asarray(self.texture.tint, np.float32)
        chroma = 1.0 + 0.03 * value_noise(X, Y, 1.3, self.seed * 13 + 3)
        rgb = alb[..., None] * tint[None, None, :]
        rgb[..., 2] *= chroma
        shadow = np.zeros((rows, cols), np.float32)

        for p, sl in pot_masks:
            rho = p.rho(X[sl], Y[sl])
            w = np.clip((1.0 - rho) / 0.15, 0.0, 1.0).astype(np.float32)
            w = w * w * (3 - 2 * w)
            r0, c0 = sl[0].start, sl[1].start
            g2 = self.texture.grey(
                x0 + c0 * gsd,
                y_top - r0 * gsd,
                gsd,
                w.shape[0],
                w.shape[1],
                seed_offset=1000 + p.seed % 1000,
                scale=0.6,
            )
            inner = (p.darken * (0.08 + 0.9 * g2))[..., None] * tint
            rgb[sl] = rgb[sl] * (1 - w[..., None]) + inner * w[..., None]
            rs = self._relief_shadow_window(p, x0 + c0 * gsd, y_top - r0 * gsd, gsd, w.shape)
            if rs is not None:
                shadow[sl] = np.maximum(shadow[sl], rs)
        for tr, sl in trough_d:
            d = tr.dist(X[sl], Y[sl], win)
            if tr.kind == "crack":
                k = np.clip(1.0 - d / (0.9 * tr.line.width), 0.0, 1.0).astype(np.float32)
                rgb[sl] *= (1.0 - 0.6 * k)[..., None]
            else:
                k = np.clip(1.0 - 2 * d / tr.line.width, 0.0, 1.0).astype(np.float32)
                rgb[sl] *= (1.0 - 0.07 * k)[..., None]
        for dd in self.distractors:
            sl = sub(dd.shape.bbox(dd.edge_m))
            if sl is None:
                continue
            m = dd.shape.soft_mask(X[sl], Y[sl], dd.edge_m).astype(np.float32)
            if dd.kind == "lane_marking":
                # Worn paint: mostly covering, with a few worn-through specks.
                wear = np.clip(
                    1.3 + 0.5 * value_noise(X[sl], Y[sl], 0.012, self.seed * 13 + 4), 0.0, 1.0
                )
                m = m * wear.astype(np.float32) * dd.strength
                paint = (0.8 + 0.1 * grey[sl])[..., None] * np.array([0.97, 0.97, 0.93], np.float32)
                rgb[sl] = rgb[sl] * (1 - m[..., None]) + paint * m[..., None]
            elif dd.kind == "oil_stain":
                k = (m * dd.strength)[..., None]
                rgb[sl] = rgb[sl] * (1 - k * np.array([1.0, 0.97, 0.9], np.float32))
            elif dd.kind == "shadow":
                shadow[sl] = np.maximum(shadow[sl], m * dd.strength)
        if c.cloud_shadow > 0:
            # Soft cloud shadows drifting over metres: part of the direct light is blocked.
            cloud = np.clip(0.5 + 0.6 * value_noise(X, Y, 4.0, self.seed * 13 + 5), 0.0, 1.0)
            shadow = 1.0 - (1.0 - shadow) * (1.0 - np.float32(c.cloud_shadow) * cloud)
        out["rgb"] = np.clip(rgb, 0.0, 1.5).astype(np.float32)
        out["shadow"] = shadow.astype(np.float32)
        return out


# --------------------------------------------------------------------------- construction


def _noise1d(t: np.ndarray, spacings: tuple[float, ...], weights: tuple[float, ...], seed: int):
    return fractal_noise(t, np.full_like(t, 0.5), spacings, weights, seed).astype(np.float64)


def build_world(cfg: SimConfig, seed: int, n_frames: int) -> World:
    """Draw a route, a trajectory and the defects/distractors for ``seed``."""
    rng = np.random.default_rng(seed)
    epsg = utm_epsg_for(cfg.origin_lat_deg, cfg.origin_lon_deg)
    en = utm_from_lla(cfg.origin_lat_deg, cfg.origin_lon_deg, epsg)[0]
    e0, n0 = float(np.round(en[0])), float(np.round(en[1]))

    # Timing and trajectory.
    fps = cfg.fps
    jitter = rng.uniform(-0.0003, 0.0003, n_frames)  # trigger jitter (s)
    jitter[0] = 0.0
    frame_times = T_START_S + np.arange(n_frames) / fps + jitter
    dt = 0.005
    t = np.arange(T_START_S - T_PAD_S, frame_times[-1] + T_PAD_S + dt, dt)
    seeds = rng.integers(0, 2**31, size=8)
    speed = cfg.speed_mps * (1.0 + cfg.speed_var * _noise1d(t, (2.5,), (1.0,), int(seeds[0])))
    s = 3.0 + np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt)])
    f = max(cfg.vibration_hz, 0.1)
    vib = math.radians(cfg.vibration_deg)
    roll = vib * _noise1d(t, (0.5 / f, 0.15 / f), (1.0, 0.5), int(seeds[1]))
    pitch = vib * _noise1d(t, (0.5 / f, 0.15 / f), (1.0, 0.5), int(seeds[2]))
    yaw = math.radians(cfg.yaw_noise_deg) * _noise1d(t, (0.8, 0.2), (1.0, 0.4), int(seeds[3]))
    dh = cfg.height_noise_m * _noise1d(t, (0.5 / f, 0.15 / f), (1.0, 0.5), int(seeds[4]))
    lateral = cfg.lateral_wander_m * _noise1d(t, (3.0,), (1.0,), int(seeds[5]))
    traj = Trajectory(t, s, speed, lateral, dh, roll, pitch, yaw)

    # Like Toronto's street grid: roughly along a cardinal direction (also keeps the north-up
    # tiles that frames render from well aligned with the footprint).
    heading0 = (
        math.radians(cfg.route_heading_deg)
        if cfg.route_heading_deg is not None
        else math.radians(90.0 * int(rng.integers(0, 4)) + rng.uniform(-5.0, 5.0))
    )
    route = Route.make(
        float(s[-1]) + 5.0,
        heading0,
        math.radians(cfg.route_curve_amp_deg),
        cfg.route_curve_wavelength_m,
        float(rng.uniform(0, 2 * np.pi)),
    )
    waves = []
    for _ in range(3):
        lam = rng.uniform(8.0, 30.0)
        ang = rng.uniform(0, 2 * np.pi)
        k = 2 * np.pi / lam
        waves.append(
            (k * math.cos(ang), k * math.sin(ang), cfg.undulation_m / 2, rng.uniform(0, 6.3))
        )
    gsd = cfg.render_gsd_m or round(cfg.camera_height_m / cfg.fx / 1.5, 5)
    world = World(
        cfg=cfg,
        seed=seed,
        n_frames=n_frames,
        epsg=epsg,
        origin_e_m=e0,
        origin_n_m=n0,
        route=route,
        traj=traj,
        frame_times=frame_times,
        texture=TextureField(cfg.texture, cfg.texel_m, cfg.texture_cell_m, gsd, seed),
        base_waves=np.asarray(waves),
        render_gsd_m=gsd,
    )
    _place_features(world, rng)
    return world


def footprint_m(cfg: SimConfig) -> tuple[float, float]:
    """Nominal ground footprint (across, along) of one frame (m)."""
    return (cfg.width / cfg.fx * cfg.camera_height_m, cfg.height / cfg.fx * cfg.camera_height_m)


def _blob(rng: np.random.Generator, cx: float, cy: float, r: float, irregular: float) -> Blob:
    k = np.arange(2, 7)
    amps = irregular * rng.uniform(0.3, 1.0, len(k)) / k**0.8
    return Blob(cx, cy, r, tuple(amps.tolist()), tuple(rng.uniform(0, 2 * np.pi, len(k)).tolist()))


def _place_features(world: World, rng: np.random.Generator) -> None:
    cfg = world.cfg
    fw, fl = footprint_m(cfg)
    s_frames = np.interp(world.frame_times, world.traj.t, world.traj.s)
    s_lo, s_hi = float(s_frames[0]), float(s_frames[-1])
    margin = min(cfg.defect_margin_m, 0.15 * (s_hi - s_lo))
    lo, hi = s_lo + margin, s_hi - margin
    occupied: list[tuple[float, float, float]] = []
    heading = world.route.heading_at

    def free(x: float, y: float, r: float) -> bool:
        return all(math.hypot(x - ox, y - oy) > r + orad + 0.08 for ox, oy, orad in occupied)

    def occupy_rect(rect: Rect) -> None:
        # Circles of the rectangle's half width along its long axis.
        n = max(2, int(rect.length / max(rect.width / 2, 0.02)) + 1)
        for a in np.linspace(-rect.length / 2, rect.length / 2, n):
            occupied.append(
                (
                    rect.cx + a * math.cos(rect.angle),
                    rect.cy + a * math.sin(rect.angle),
                    rect.width / 2,
                )
            )

    def spot(r: float, lat_max: float | None = None, tries: int = 300):
        lm = max(0.03, 0.5 * fw - r - 0.08) if lat_max is None else lat_max
        for _ in range(tries):
            s = rng.uniform(lo, hi)
            lat = float(world.camera_path_lateral(np.array([s]))[0]) + rng.uniform(-lm, lm)
            x, y = world.route.point(np.array([s]), np.array([lat]))[0]
            if free(x, y, r):
                return s, lat, float(x), float(y)
        return None

    # Long features first (markings, ruts), then potholes and cracks fit around them.
    for _ in range(cfg.n_lane_markings):
        u = rng.uniform()
        dashed = cfg.marking_style == "dashed" or (cfg.marking_style == "mixed" and u < 0.7)
        if dashed:  # dashed longitudinal line near the image edge
            side = rng.choice([-1.0, 1.0])
            off = side * rng.uniform(0.25, 0.42)
            width = rng.uniform(0.10, 0.15)
            dash, gap = rng.uniform(1.0, 3.0), rng.uniform(1.0, 2.5)
            sec = min(rng.uniform(4.0, 9.0), hi - lo)
            s = rng.uniform(lo, max(lo, hi - sec))
            end = s + sec
            while s < end:
                sc = s + dash / 2
                ss = np.linspace(s, s + dash, max(7, int(dash / 0.1) | 1))
                pts = world.route.point(ss, np.full_like(ss, off))
                if all(free(px, py, width / 2) for px, py in pts):
                    cx, cy = pts[len(pts) // 2]
                    ang = math.pi / 2 - float(heading(np.array([sc]))[0])
                    world.distractors.append(
                        Distractor(
                            "lane_marking",
                            Rect(float(cx), float(cy), ang, dash, width),
                            float(rng.uniform(0.85, 1.0)),
                            0.003,
                        )
                    )
                    occupied.extend((float(px), float(py), width / 2) for px, py in pts)
                s += dash + gap
        else:  # transverse stop bar across the whole footprint
            width = rng.uniform(0.3, 0.45)
            sp = spot(width / 2, lat_max=0.05)
            if sp is None:
                continue
            s, _, x, y = sp
            ang = -float(heading(np.array([s]))[0])  # perpendicular to travel
            rect = Rect(x, y, ang, fw + 0.6, width)
            occupy_rect(rect)
            world.distractors.append(
                Distractor("lane_marking", rect, float(rng.uniform(0.85, 1.0)), 0.003)
            )

    for i in range(cfg.n_ruts):
        placed = False
        for _ in range(60):
            length = min(rng.uniform(3.0, 7.0), 0.8 * (hi - lo))
            s0 = rng.uniform(lo, max(lo, hi - length))
            width = rng.uniform(0.35, 0.6)
            off = rng.uniform(-0.25, 0.25)
            ss = np.arange(s0, s0 + length + 1e-9, 0.25)
            pts = world.route.point(ss, world.camera_path_lateral(ss) + off)
            if all(free(px, py, width / 2) for px, py in pts):
                placed = True
                break
        if not placed:
            log.warning("could not place rut %d without overlap; skipped", i)
            continue
        occupied.extend((float(px), float(py), width / 2) for px, py in pts)
        line = Polyline(tuple(map(tuple, pts.tolist())), float(width))
        world.troughs.append(Trough("rut", line, float(rng.uniform(0.008, 0.02)), 0.8))

    # Potholes: stratified sizes and depths so a drive holds small/large, shallow/deep ones.
    n = cfg.n_potholes
    s0, s1 = cfg.pothole_size_m
    d0, d1 = cfg.pothole_depth_m
    sizes = s0 + (s1 - s0) * (np.arange(n) + rng.uniform(0.1, 0.9, n)) / max(n, 1)
    depths = d0 + (d1 - d0) * (rng.permutation(n) + rng.uniform(0.1, 0.9, n)) / max(n, 1)
    for i in range(n):
        irregular = rng.uniform(0.15, 0.35)
        r = sizes[i] / 2 / (1 + 0.3 * irregular)
        sp = spot(r * (1 + irregular))
        if sp is None:
            log.warning("could not place pothole %d without overlap; skipped", i)
            continue
        _, _, x, y = sp
        b = _blob(rng, x, y, r, irregular)
        occupied.append((x, y, b.r_max))
        pot = Pothole(
            shape=b,
            depth_m=float(depths[i]),
            power=float(rng.uniform(*cfg.pothole_power)),
            tilt=(float(rng.uniform(-0.15, 0.15)), float(rng.uniform(-0.15, 0.15))),
            rough_m=float(0.06 * depths[i] + 0.001),
            darken=float(rng.uniform(*cfg.pothole_darken)),
            seed=int(rng.integers(0, 2**31)),
        )
        # Tilt and roughness add to the nominal depth: rescale so the true maximum is the drawn
        # depth (the profile is linear in depth_m and rough_m, so the maximum scales exactly).
        x0b, y0b, x1b, y1b = pot.bbox(0.002)
        gx, gy = np.meshgrid(
            np.arange(x0b, x1b, 0.001) + 0.0005, np.arange(y0b, y1b, 0.001) + 0.0005
        )
        f = float(depths[i]) / max(float(pot.depth(gx, gy).max()), 1e-6)
        world.potholes.append(
            dataclasses.replace(pot, depth_m=pot.depth_m * f, rough_m=pot.rough_m * f)
        )

    for i in range(cfg.n_cracks):
        length = rng.uniform(0.5, 1.4)
        sp = spot(length / 2, lat_max=max(0.03, 0.5 * fw - length / 2))
        if sp is None:
            log.warning("could not place crack %d; skipped", i)
            continue
        s, _, x, y = sp
        ang = math.pi / 2 - float(heading(np.array([s]))[0]) + rng.choice([0.0, math.pi / 2])
        ang += rng.uniform(-0.5, 0.5)
        nseg = max(4, int(length / 0.04))
        angs = ang + np.cumsum(rng.normal(0, 0.18, nseg))
        steps = np.column_stack([np.cos(angs), np.sin(angs)]) * (length / nseg)
        pts = np.vstack([[0.0, 0.0], np.cumsum(steps, axis=0)])
        pts = pts - pts.mean(axis=0) + [x, y]
        width = rng.uniform(0.003, 0.008)
        line = Polyline(tuple(map(tuple, pts.tolist())), float(width))
        occupied.append((x, y, length / 2 + 0.02))
        world.troughs.append(Trough("crack", line, float(rng.uniform(0.002, 0.006)), 0.0))

    for i in range(cfg.n_shadows):
        if rng.uniform() < 0.5:  # pole shadow: a long soft strip across the road
            width = rng.uniform(0.12, 0.25)
            sp = spot(width / 2 + 0.1, lat_max=0.1)
            if sp is None:
                log.warning("could not place shadow %d; skipped", i)
                continue
            s, _, x, y = sp
            ang = -float(heading(np.array([s]))[0]) + rng.uniform(-0.6, 0.6)
            shape: Blob | Rect = Rect(x, y, ang, fw + 1.0, width)
            occupy_rect(shape)
        else:  # tree / sign shadow blob
            r = rng.uniform(0.2, 0.4)
            sp = spot(r * 1.4)
            if sp is None:
                log.warning("could not place shadow %d; skipped", i)
                continue
            _, _, x, y = sp
            shape = _blob(rng, x, y, r, 0.5)
            occupied.append((x, y, shape.r_max))
        world.distractors.append(
            Distractor(
                "shadow", shape, float(rng.uniform(0.55, 0.8)), float(rng.uniform(0.02, 0.04))
            )
        )

    for i in range(cfg.n_oil_stains):
        r = rng.uniform(0.08, 0.22)
        sp = spot(r * 1.5)
        if sp is None:
            log.warning("could not place oil stain %d; skipped", i)
            continue
        _, _, x, y = sp
        b = _blob(rng, x, y, r, 0.6)
        occupied.append((x, y, b.r_max))
        world.distractors.append(
            Distractor(
                "oil_stain", b, float(rng.uniform(0.35, 0.6)), float(rng.uniform(0.01, 0.03))
            )
        )
