"""Seeded synthetic scenes for detection tests: a noisy road plane with bowl potholes, image-only
distractors (lane marking, shadow), tiny rendered images, pair point clouds and poses.

The vehicle drives north along the ENU y axis with the camera ``height_m`` above the road; each
pair's points are sampled on the true surface inside frame a's footprint and expressed in
camera-a coordinates with Gaussian noise, like a reconstruction would give them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from roadsurf.core.geometry import EnuReference, invert_pose, transform_points, world_from_cam
from roadsurf.io.drive import Camera, Drive, Frame
from roadsurf.mapping.types import Trajectory
from roadsurf.reconstruction.types import PairResult

REF = EnuReference(lat_deg=43.0, lon_deg=-79.5, alt_m=100.0)


@dataclass
class Pothole:
    x_m: float
    y_m: float
    radius_m: float
    depth_m: float
    darker: float = 0.65  # image intensity factor inside (real potholes are darker)


@dataclass
class Trough:
    """A straight crack or rut from (x0, y0) to (x1, y1) with a parabolic cross-section."""

    x0_m: float
    y0_m: float
    x1_m: float
    y1_m: float
    width_m: float
    depth_m: float
    darker: float = 1.0  # image intensity factor inside (cracks are dark lines)
    # "flat": the same factor across the groove (a painted band); "floor": darkest at the
    # floor and 1 at the rims, (1 - q²) like the depth (the walls shade the floor from the sky)
    dark_profile: str = "flat"

    def darkness(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Intensity factor at ENU x, y (1 outside the groove)."""
        a, b = np.array([self.x0_m, self.y0_m]), np.array([self.x1_m, self.y1_m])
        L = float(np.linalg.norm(b - a))
        ux, uy = (b - a) / L
        s_ = (x - a[0]) * ux + (y - a[1]) * uy
        q = 2.0 * (-(x - a[0]) * uy + (y - a[1]) * ux) / self.width_m
        inside = (s_ >= 0) & (s_ <= L) & (np.abs(q) < 1.0)
        k = np.clip(1.0 - q * q, 0.0, 1.0) if self.dark_profile == "floor" else 1.0
        return np.where(inside, 1.0 - (1.0 - self.darker) * k, 1.0)


@dataclass
class Scene:
    potholes: list[Pothole] = field(default_factory=list)
    troughs: list[Trough] = field(default_factory=list)
    lane_x_m: float | None = None  # bright lane marking: |x - lane_x| < 0.05 m, no depth
    shadow_x_m: float | None = None  # dark shadow for x > shadow_x, no depth
    oil_xy_m: tuple[float, float] | None = None  # dark oil stain disc r = 0.1 m, no depth
    noise_m: float = 0.0005  # σ of the point depths

    def depth(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Depth below the road (m, positive down) at ENU x, y."""
        d = np.zeros(np.broadcast(x, y).shape)
        for p in self.potholes:
            r2 = ((x - p.x_m) ** 2 + (y - p.y_m) ** 2) / p.radius_m**2
            d = np.maximum(d, p.depth_m * np.clip(1.0 - r2, 0.0, None))
        for t in self.troughs:
            a = np.array([t.x0_m, t.y0_m])
            b = np.array([t.x1_m, t.y1_m])
            L = float(np.linalg.norm(b - a))
            ux, uy = (b - a) / L
            s_ = (x - a[0]) * ux + (y - a[1]) * uy
            n_ = -(x - a[0]) * uy + (y - a[1]) * ux
            prof = t.depth_m * np.clip(1.0 - (2.0 * n_ / t.width_m) ** 2, 0.0, None)
            d = np.maximum(d, np.where((s_ >= 0) & (s_ <= L), prof, 0.0))
        return d

    def intensity(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Grey level of the road texture at ENU x, y."""
        g = 120.0 + 18.0 * np.sin(37.0 * x + 3.0 * np.sin(23.0 * y)) * np.cos(29.0 * y + 1.3 * x)
        g = g + 10.0 * np.sin(91.0 * x * y + 5.0 * x)
        for p in self.potholes:
            inside = (x - p.x_m) ** 2 + (y - p.y_m) ** 2 < p.radius_m**2
            g = np.where(inside, g * p.darker, g)
        for t in self.troughs:
            if t.darker != 1.0:
                a = np.array([t.x0_m, t.y0_m])
                b = np.array([t.x1_m, t.y1_m])
                L = float(np.linalg.norm(b - a))
                ux, uy = (b - a) / L
                s_ = (x - a[0]) * ux + (y - a[1]) * uy
                n_ = -(x - a[0]) * uy + (y - a[1]) * ux
                inside = (s_ >= 0) & (s_ <= L) & (np.abs(n_) < 0.5 * t.width_m)
                g = np.where(inside, g * t.darker, g)
        if self.lane_x_m is not None:
            g = np.where(np.abs(x - self.lane_x_m) < 0.05, 235.0, g)
        if self.shadow_x_m is not None:
            g = np.where(x > self.shadow_x_m, g * 0.45, g)
        if self.oil_xy_m is not None:
            ox, oy = self.oil_xy_m
            g = np.where((x - ox) ** 2 + (y - oy) ** 2 < 0.1**2, g * 0.5, g)
        return np.clip(g, 0, 255)


CAMERA = Camera(width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5, height_m=1.0, fps=10.0)


def poses(n_frames: int, step_m: float = 0.4, h: float = 1.0) -> np.ndarray:
    """(N, 4, 4) world_from_cam, driving north from y = 0."""
    return np.stack(
        [
            world_from_cam(0.0, position_enu_m=np.array([0.0, k * step_m, h]))
            for k in range(n_frames)
        ]
    )


def _ground_xy(T: np.ndarray, camera: Camera, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    rays = np.linalg.solve(camera.K, np.vstack([u, v, np.ones_like(u)]))
    rw = T[:3, :3] @ rays
    s = -T[2, 3] / rw[2]
    return (T[:3, 3][:, None] + rw * s)[:2].T


def render(scene: Scene, T: np.ndarray, camera: Camera = CAMERA) -> np.ndarray:
    """(H, W) uint8 image of the road seen from pose T (flat-ground approximation)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(float)
    xy = _ground_xy(T, camera, u.ravel(), v.ravel())
    return scene.intensity(xy[:, 0], xy[:, 1]).reshape(camera.height, camera.width).astype(np.uint8)


def pair_points(
    scene: Scene,
    T_a: np.ndarray,
    rng: np.random.Generator,
    n_points: int = 2500,
    camera: Camera = CAMERA,
    keep=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Points on the true surface inside frame a's view: (N, 3) camera-a coords, (N, 2) px."""
    u = rng.uniform(0, camera.width - 1, n_points)
    v = rng.uniform(0, camera.height - 1, n_points)
    xy = _ground_xy(T_a, camera, u, v)
    if keep is not None:
        m = keep(xy[:, 0], xy[:, 1])
        xy = xy[m]
    z = -scene.depth(xy[:, 0], xy[:, 1]) + rng.normal(0, scene.noise_m, len(xy))
    Pw = np.column_stack([xy, z])
    Pc = transform_points(invert_pose(T_a), Pw)
    px = (Pc @ camera.K.T)[:, :2] / Pc[:, 2:3]
    return Pc, px


def build(
    scene: Scene,
    root: Path,
    n_frames: int = 6,
    seed: int = 0,
    georeferenced: bool = True,
    keep_per_pair=None,
    n_points: int = 2500,
    camera: Camera = CAMERA,
    step_m: float = 0.4,
) -> tuple[Drive, list[PairResult], Trajectory]:
    """Write tiny images under ``root/frames`` and return (drive, pairs, trajectory)
    (``camera`` and the spacing ``step_m`` of the frames along y: the defaults' 160 x 120 px
    at 6.7 mm and 0.4 m)."""
    from roadsurf.core.fits import fit_plane_z, plane_signed_distance

    rng = np.random.default_rng(seed)
    Ts = poses(n_frames, step_m=step_m, h=camera.height_m)
    (root / "frames").mkdir(parents=True, exist_ok=True)
    frames = []
    for k, T in enumerate(Ts):
        fn = f"{k:06d}.png"
        cv2.imwrite(str(root / "frames" / fn), render(scene, T, camera))
        frames.append(Frame(k, fn, root / "frames" / fn, 0.1 * k))
    drive = Drive(root, camera, frames, gps=None, obd=None)
    pairs = []
    for k in range(n_frames - 1):
        keep = keep_per_pair(k) if keep_per_pair is not None else None
        Pc, px = pair_points(scene, Ts[k], rng, n_points, keep=keep, camera=camera)
        plane = fit_plane_z(Pc)
        pairs.append(
            PairResult(
                frame_a=frames[k].filename,
                frame_b=frames[k + 1].filename,
                index_a=k,
                index_b=k + 1,
                method="proposed",
                status="ok",
                points_cam_a_m=Pc,
                px_a=px,
                px_b=px,
                cov_m2=np.zeros((len(Pc), 3, 3)),
                plane_dist_m=plane_signed_distance(Pc, plane),
                plane=plane,
            )
        )
    traj = Trajectory(
        filenames=[f.filename for f in frames],
        frame_indices=np.arange(n_frames),
        timestamp_s=np.arange(n_frames) * 0.1,
        world_from_cam=Ts,
        source=["gps"] * n_frames,
        reference=REF if georeferenced else None,
    )
    return drive, pairs, traj


def write_surface(scene: Scene, run_dir: Path, traj: Trajectory, gsd_m: float = 0.005, seed=0):
    """RUN/surface.tif as mapping writes it: residual (m, negative below) on a UTM grid over the
    driven corridor, with measurement noise; returns the GridSpec."""
    from roadsurf.core.geometry import ExportFrame, enu_from_lla, lla_from_utm
    from roadsurf.io.formats import GridSpec, write_geotiff

    ef = ExportFrame.for_reference(REF)
    pos = traj.positions_enu_m
    corners = np.array(
        [
            [pos[:, 0].min() - 0.7, pos[:, 1].min() - 0.6, 0],
            [pos[:, 0].max() + 0.7, pos[:, 1].max() + 0.6, 0],
        ]
    )
    en = ef.utm_from_enu(corners)[:, :2]
    x0, y0 = np.floor(en[:, 0].min()), np.ceil(en[:, 1].max())
    w = int(np.ceil((en[:, 0].max() - x0) / gsd_m))
    h = int(np.ceil((y0 - en[:, 1].min()) / gsd_m))
    grid = GridSpec(ef.crs, float(x0), float(y0), gsd_m, w, h)
    rr, cc = np.mgrid[0:h, 0:w]
    xy = grid.xy_from_rowcol(rr.ravel(), cc.ravel())
    lla = lla_from_utm(xy[:, 0], xy[:, 1], ef.epsg)
    enu = enu_from_lla(lla[:, 0], lla[:, 1], REF.alt_m, REF)
    rng = np.random.default_rng(seed)
    res = -scene.depth(enu[:, 0], enu[:, 1]) + rng.normal(0, scene.noise_m, len(enu))
    res = res.reshape(h, w).astype(np.float32)
    res[np.abs(enu[:, 0].reshape(h, w)) > 0.55] = np.nan  # outside the imaged corridor
    write_geotiff(run_dir / "surface.tif", res, grid, nodata=float("nan"))
    return grid


def write_truth(scene: Scene, truth_dir: Path, traj: Trajectory, camera: Camera = CAMERA) -> None:
    """A simulator-style truth folder for the scene: scenario.json, poses.csv, frame_labels.csv,
    defects.geojson (pothole discs) and distractors.geojson (lane marking, oil stain)."""
    import json

    from roadsurf.core.geometry import ExportFrame
    from roadsurf.io.formats import feature, polygon_geometry, write_csv, write_geojson

    truth_dir.mkdir(parents=True, exist_ok=True)
    ef = ExportFrame.for_reference(REF)
    (truth_dir / "scenario.json").write_text(
        json.dumps({"scenario": "synthetic", "seed": 0, "crs": ef.crs, "n_frames": len(traj)})
    )
    en = ef.utm_from_enu(traj.positions_enu_m)
    write_csv(
        truth_dir / "poses.csv",
        ["filename", "easting_m", "northing_m"],
        [(f, e, n) for f, (e, n, _) in zip(traj.filenames, en, strict=True)],
    )
    rows = []
    g = np.arange(-1.0, 3.5, 0.005)
    gx, gy = np.meshgrid(np.arange(-0.7, 0.7, 0.005), g)
    deep = scene.depth(gx, gy) > 0.010
    from matplotlib.path import Path as MplPath

    for f, T in zip(traj.filenames, traj.world_from_cam, strict=True):
        fp = camera.footprint_corners_enu(T)
        inside = MplPath(fp).contains_points(np.column_stack([gx[deep], gy[deep]]))
        area = inside.sum() * 0.005**2
        rows.append((f, int(area >= 0.002), area * 1e4, 0.0))
    write_csv(
        truth_dir / "frame_labels.csv",
        ["filename", "defect", "defect_area_cm2", "max_depth_m"],
        rows,
    )
    feats = []
    for i, p in enumerate(scene.potholes, start=1):
        a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        ring = np.column_stack([p.x_m + p.radius_m * np.cos(a), p.y_m + p.radius_m * np.sin(a)])
        props = {
            "id": i,
            "type": "pothole",
            "max_depth_m": p.depth_m,
            "mean_depth_m": p.depth_m / 2,
            "area_m2": np.pi * p.radius_m**2,
            "volume_m3": np.pi * p.radius_m**2 * p.depth_m / 2,
            "length_m": 2 * p.radius_m,
            "width_m": 2 * p.radius_m,
        }
        feats.append(feature(polygon_geometry(ef.lonlat_from_enu(ring)), props))
    write_geojson(truth_dir / "defects.geojson", feats)
    dis = []
    if scene.lane_x_m is not None:
        x = scene.lane_x_m
        ring = np.array([[x - 0.05, -1.0], [x + 0.05, -1.0], [x + 0.05, 3.0], [x - 0.05, 3.0]])
        dis.append(feature(polygon_geometry(ef.lonlat_from_enu(ring)), {"type": "lane_marking"}))
    if scene.oil_xy_m is not None:
        a = np.linspace(0, 2 * np.pi, 32, endpoint=False)
        ring = np.column_stack(
            [scene.oil_xy_m[0] + 0.1 * np.cos(a), scene.oil_xy_m[1] + 0.1 * np.sin(a)]
        )
        dis.append(feature(polygon_geometry(ef.lonlat_from_enu(ring)), {"type": "oil_stain"}))
    write_geojson(truth_dir / "distractors.geojson", dis)


def _random_texture(
    seed: int, size_m: float = 3.0, res_m: float = 0.002
) -> tuple[np.ndarray, float]:
    """A seeded random grey texture (blurred noise, 2 mm cells) and its half size (m)."""
    n = int(size_m / res_m)
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (n, n)).astype(np.float32), (0, 0), 1.5)
    tex = 128.0 + 40.0 * tex / max(float(tex.std()), 1e-6)
    return tex.astype(np.float32), size_m / 2


def render_relief(
    scene: Scene, T: np.ndarray, camera: Camera, tex: tuple[np.ndarray, float]
) -> np.ndarray:
    """(H, W) uint8 image of the road WITH its relief seen from pose T: each pixel's ray is cast
    onto the surface z = -depth(x, y) (fixed-point iteration), so potholes show true parallax
    between views; texture fixed to the ground, potholes darker (``Pothole.darker``)."""
    img, half = tex
    res = 2 * half / img.shape[0]
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(float)
    rays = T[:3, :3] @ np.linalg.solve(camera.K, np.vstack([u.ravel(), v.ravel(), np.ones(u.size)]))
    rays = rays / -rays[2]  # unit drop in z per step
    s = np.full(u.size, T[2, 3])
    for _ in range(40):
        x = T[0, 3] + s * rays[0]
        y = T[1, 3] + s * rays[1]
        s = 0.5 * s + 0.5 * (T[2, 3] + scene.depth(x, y))
    x = T[0, 3] + s * rays[0]
    y = T[1, 3] + s * rays[1]
    mx = ((x + half) / res).astype(np.float32).reshape(u.shape)
    my = ((y + half) / res).astype(np.float32).reshape(u.shape)
    g = cv2.remap(img, mx, my, cv2.INTER_LINEAR)
    for p in scene.potholes:
        inside = ((x - p.x_m) ** 2 + (y - p.y_m) ** 2 < p.radius_m**2).reshape(u.shape)
        g = np.where(inside, g * p.darker, g)
    # Dark grooves / painted lines: darkness on the surface hit, averaged over 4 x 4 samples
    # per pixel (a camera integrates over its pixel; a hard edge would snap a 4 px line to
    # the pixel grid). The samples are placed with the local ground-per-pixel Jacobian.
    dark = [t for t in scene.troughs if t.darker != 1.0]
    if dark:
        X, Y = x.reshape(u.shape), y.reshape(u.shape)
        dxu, dxv = np.gradient(X, axis=1), np.gradient(X, axis=0)
        dyu, dyv = np.gradient(Y, axis=1), np.gradient(Y, axis=0)
        sub = (np.arange(4) + 0.5) / 4 - 0.5
        for t in dark:
            f = np.zeros(u.shape)
            for du in sub:
                for dv in sub:
                    f += t.darkness(X + du * dxu + dv * dxv, Y + du * dyu + dv * dyv)
            g = g * (f / 16.0)
    return np.clip(g, 0, 255).astype(np.uint8)


def build_two_view(
    scene: Scene,
    root: Path,
    step_m: float = 0.25,
    seed: int = 0,
    camera: Camera | None = None,
    max_feature_depth_m: float = 0.012,
    turn_b_deg: float = 0.0,
) -> tuple[Drive, list[PairResult], Trajectory]:
    """Two frames rendered with true relief and ONE pair whose sparse matches (with exact
    R, t, H) avoid the pothole floor: features only where the surface is shallower than
    ``max_feature_depth_m`` (a dark, smooth pothole bottom holds no features). Camera b is
    turned by ``turn_b_deg`` about the vertical (a photographer turning between shots)."""
    from roadsurf.core.fits import fit_plane_z, plane_signed_distance

    cam = camera or Camera(
        width=320, height=240, fx=300.0, fy=300.0, cx=159.5, cy=119.5, height_m=1.0, fps=10.0
    )
    rng = np.random.default_rng(seed)
    Ts = poses(2, step_m=step_m, h=cam.height_m)
    Ts[1] = world_from_cam(turn_b_deg, position_enu_m=Ts[1][:3, 3])
    tex = _random_texture(seed)
    (root / "frames").mkdir(parents=True, exist_ok=True)
    frames = []
    for k, T in enumerate(Ts):
        fn = f"{k:06d}.png"
        cv2.imwrite(str(root / "frames" / fn), render_relief(scene, T, cam, tex))
        frames.append(Frame(k, fn, root / "frames" / fn, 0.1 * k))
    drive = Drive(root, cam, frames, gps=None, obd=None)
    # Features: random pixels of a, their true surface points, kept off the floor, seen in b.
    n = 3000
    u = rng.uniform(0, cam.width - 1, n)
    v = rng.uniform(0, cam.height - 1, n)
    rays = Ts[0][:3, :3] @ np.linalg.solve(cam.K, np.vstack([u, v, np.ones(n)]))
    rays = rays / -rays[2]
    s = np.full(n, Ts[0][2, 3])
    for _ in range(40):
        s = 0.5 * s + 0.5 * (
            Ts[0][2, 3] + scene.depth(Ts[0][0, 3] + s * rays[0], Ts[0][1, 3] + s * rays[1])
        )
    Pw = (Ts[0][:3, 3][:, None] + s * rays).T
    keep = scene.depth(Pw[:, 0], Pw[:, 1]) < max_feature_depth_m
    Pw = Pw[keep]
    Pa = transform_points(invert_pose(Ts[0]), Pw)
    Pb = transform_points(invert_pose(Ts[1]), Pw)
    px_a = (Pa @ cam.K.T)[:, :2] / Pa[:, 2:3]
    px_b = (Pb @ cam.K.T)[:, :2] / Pb[:, 2:3]
    inb = (
        (px_b[:, 0] >= 0) & (px_b[:, 0] < cam.width) & (px_b[:, 1] >= 0) & (px_b[:, 1] < cam.height)
    )
    Pa, px_a, px_b = Pa[inb] + rng.normal(0, scene.noise_m, (inb.sum(), 3)), px_a[inb], px_b[inb]
    T_ba = invert_pose(Ts[1]) @ Ts[0]
    R, t = T_ba[:3, :3], T_ba[:3, 3]
    # Road plane in camera a: Z = h (camera z points down at the road), n = (0, 0, 1), d = h.
    H = cam.K @ (R + np.outer(t, [0.0, 0.0, 1.0]) / cam.height_m) @ np.linalg.inv(cam.K)
    plane = fit_plane_z(Pa)
    pair = PairResult(
        frame_a=frames[0].filename,
        frame_b=frames[1].filename,
        index_a=0,
        index_b=1,
        method="proposed",
        status="ok",
        points_cam_a_m=Pa,
        px_a=px_a,
        px_b=px_b,
        cov_m2=np.zeros((len(Pa), 3, 3)),
        plane_dist_m=plane_signed_distance(Pa, plane),
        plane=plane,
        R_b_from_a=R,
        t_b_from_a_m=t,
        H=H / H[2, 2],
    )
    traj = Trajectory(
        filenames=[f.filename for f in frames],
        frame_indices=np.arange(2),
        timestamp_s=np.arange(2) * 0.1,
        world_from_cam=Ts,
        source=["gps"] * 2,
        reference=REF,
    )
    return drive, [pair], traj
