"""Place the defects and distractors of a world without overlaps, within the camera's
footprint along the path: lane markings and ruts first, then potholes, cracks, shadows and oil
stains fit around them."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from roadsurf.core.geometry import world_from_cam
from roadsurf.simulation.config import SimConfig
from roadsurf.simulation.defects import Distractor, Pothole, Trough
from roadsurf.simulation.shapes import Blob, Polyline, Rect
from roadsurf.simulation.world import World

log = logging.getLogger(__name__)


def footprint_m(cfg: SimConfig) -> tuple[float, float]:
    """Nominal ground footprint (across, along) of one frame (m); for a tilted mount the band
    every part of the footprint covers (its narrow near edge across, its shortest side along)."""
    if not cfg.mounted:
        return (
            cfg.width / cfg.fx * cfg.camera_height_m,
            cfg.height / cfg.fx * cfg.camera_height_m,
        )
    x, y = _level_corners(cfg)
    return min(x[1], x[2]) - max(x[0], x[3]), min(y[0], y[1]) - max(y[2], y[3])


def footprint_offset_m(cfg: SimConfig) -> tuple[float, float, float]:
    """(right, ahead, widest across) of the nominal footprint (m): the centre of the band of
    ``footprint_m`` to the right of and ahead of the camera, and the footprint's full width
    (all 0, 0, across for the nadir camera)."""
    if not cfg.mounted:
        return 0.0, 0.0, footprint_m(cfg)[0]
    x, y = _level_corners(cfg)
    right = 0.5 * (min(x[1], x[2]) + max(x[0], x[3]))
    ahead = 0.5 * (min(y[0], y[1]) + max(y[2], y[3]))
    return right, ahead, max(x) - min(x)


def _level_corners(cfg: SimConfig) -> tuple[list[float], list[float]]:
    """Image corners (top-left, top-right, bottom-right, bottom-left) on a flat road for a
    level vehicle heading north: x to its right, y ahead of the camera (m)."""
    T = world_from_cam(0.0)
    T[:3, :3] = T[:3, :3] @ cfg.vehicle_from_cam()
    xy = cfg.camera().footprint_corners_enu(T)
    if xy is None:  # check_view refuses such a mount before anything is placed
        raise ValueError("a corner ray of the mounted camera misses the road")
    return [float(v) for v in xy[:, 0]], [float(v) for v in xy[:, 1]]


def _blob(rng: np.random.Generator, cx: float, cy: float, r: float, irregular: float) -> Blob:
    k = np.arange(2, 7)
    amps = irregular * rng.uniform(0.3, 1.0, len(k)) / k**0.8
    return Blob(cx, cy, r, tuple(amps.tolist()), tuple(rng.uniform(0, 2 * np.pi, len(k)).tolist()))


def place_features(world: World, rng: np.random.Generator) -> None:
    """Append ``world``'s defects and distractors, drawn from ``rng`` (in place)."""
    cfg = world.cfg
    fw, fl = footprint_m(cfg)
    # A tilted or turned camera sees the road ahead of / beside itself: place there.
    right, ahead, fw_outer = footprint_offset_m(cfg)
    s_frames = np.interp(world.frame_times, world.traj.t, world.traj.s)
    s_lo, s_hi = float(s_frames[0]), float(s_frames[-1])
    margin = min(cfg.defect_margin_m, 0.15 * (s_hi - s_lo))
    lo, hi = s_lo + margin + ahead, s_hi - margin + ahead
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
            lat = float(world.camera_path_lateral(np.array([s]))[0]) + right + rng.uniform(-lm, lm)
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
            off = side * rng.uniform(0.25, 0.42) + right
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
            rect = Rect(x, y, ang, fw_outer + 0.6, width)
            occupy_rect(rect)
            world.distractors.append(
                Distractor("lane_marking", rect, float(rng.uniform(0.85, 1.0)), 0.003)
            )

    for i in range(cfg.n_ruts):
        if 0.8 * (hi - lo) < 0.25:  # a rut needs two points 0.25 m apart along the path
            log.warning("could not place rut %d: the drive is too short; skipped", i)
            continue
        placed = False
        for _ in range(60):
            length = min(rng.uniform(3.0, 7.0), 0.8 * (hi - lo))
            s0 = rng.uniform(lo, max(lo, hi - length))
            width = rng.uniform(0.35, 0.6)
            off = rng.uniform(-0.25, 0.25)
            ss = np.arange(s0, s0 + length + 1e-9, 0.25)
            pts = world.route.point(ss, world.camera_path_lateral(ss) + right + off)
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
            shape: Blob | Rect = Rect(x, y, ang, fw_outer + 1.0, width)
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
