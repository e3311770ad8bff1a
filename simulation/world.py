"""The simulated world: the road surface (height + appearance) with its defects and depth-less
distractors, seen along the route by the camera's continuous trajectory.

Coordinates: local metric x (east), y (north), z (up), metres, relative to a UTM origin
(``World.origin_e_m``, ``World.origin_n_m``, ``cfg.origin_alt_m``) in the scenario's UTM CRS. The
world is a pure function of (config, seed): any window of it can be evaluated on demand
(``World.evaluate``), so frames render local patches and the truth raster is written block by
block, and memory scales with the road corridor, never with the bounding box of the route.
``build.build_world`` draws a world for a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from roadsurf.core.geometry import lla_from_utm, world_from_cam
from roadsurf.simulation.config import SimConfig
from roadsurf.simulation.defects import Distractor, Pothole, Trough
from roadsurf.simulation.noise import fractal_noise, value_noise
from roadsurf.simulation.route import Pose, Route, Trajectory
from roadsurf.simulation.texture import TextureField

TRACK_M = 1.6  # wheel track of the simulated vehicle (m): its body's roll on the road
WHEELBASE_M = 2.8  # axle distance of the simulated vehicle (m): its body's pitch on the road


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
    _lateral_slope: np.ndarray | None = field(default=None, repr=False)  # (T,) d lateral / ds

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
        # the nose follows the path: the lateral wander turns the vehicle by its slope
        # d(lateral)/ds (+ = moving right = clockwise); without it the vehicle crabbed by that
        # slope (a 36-frame drive: 0.2-0.3°, which roadsurf reads, rightly, as mount yaw)
        hd += math.degrees(math.atan(float(np.interp(t, tr.t, self.lateral_slope()))))
        roll = float(np.interp(t, tr.t, tr.roll))
        # a vehicle's body follows the road: pitched nose-up by the road's slope along its
        # heading between its axles (WHEELBASE_M; grade and long-wave undulation), plus the
        # vibration. Without it the camera kept its pitch over a 1 % grade, where roadsurf
        # (mapping.grade) tips a camera.yaml mount by the grade the GPS heights give
        h = math.radians(hd)
        dx, dy = 0.5 * WHEELBASE_M * math.sin(h), 0.5 * WHEELBASE_M * math.cos(h)
        front = float(self.base(np.array(xy[0] + dx), np.array(xy[1] + dy)))
        rear = float(self.base(np.array(xy[0] - dx), np.array(xy[1] - dy)))
        pitch = float(np.interp(t, tr.t, tr.pitch)) + math.atan((front - rear) / WHEELBASE_M)
        if c.roll_with_road:  # the right wheels lower: roll < 0 (world_from_cam's sign)
            rx, ry = 0.5 * TRACK_M * math.cos(h), -0.5 * TRACK_M * math.sin(h)
            right = float(self.base(np.array(xy[0] + rx), np.array(xy[1] + ry)))
            left = float(self.base(np.array(xy[0] - rx), np.array(xy[1] - ry)))
            roll += math.atan((right - left) / TRACK_M)
        # The vehicle's pose (a nadir camera's) times the mount; the centre stays at C.
        T = world_from_cam(hd % 360.0, roll, pitch, np.array([xy[0], xy[1], z]))
        R = T[:3, :3] @ c.vehicle_from_cam() if c.mounted else T[:3, :3].copy()
        return Pose(t, T[:3, 3].copy(), R, hd % 360.0, roll, pitch)

    def lateral_slope(self) -> np.ndarray:
        """(T,) d(lateral)/d(arc length) along the dense trajectory (-), computed once."""
        if self._lateral_slope is None:
            tr = self.traj
            ds, dl = np.gradient(tr.s, tr.t), np.gradient(tr.lateral, tr.t)
            moving = np.abs(ds) > 1e-6
            self._lateral_slope = np.where(moving, dl / np.where(moving, ds, 1.0), 0.0)
        return self._lateral_slope

    def camera_path_lateral(self, s: np.ndarray) -> np.ndarray:
        """Lateral offset of the camera where it first passes arc length s (m): a revisit's
        arc length goes back (``SimConfig.revisit_after_s``), so only its first pass is read."""
        tr = self.traj
        back = np.flatnonzero(np.diff(tr.s) < 0)
        n = int(back[0]) + 1 if len(back) else len(tr.s)
        return np.interp(s, tr.s[:n], tr.lateral[:n])

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
