"""Draw a world for a seed: timing, trajectory, route, long-wave undulation, then the
defects and distractors (``placement``). The order of the random draws is part of the
output: every scenario's drive is a pure function of (config, seed)."""

from __future__ import annotations

import math

import numpy as np

from roadsurf.core.errors import ConfigError
from roadsurf.core.geometry import utm_epsg_for, utm_from_lla
from roadsurf.simulation.config import SimConfig
from roadsurf.simulation.noise import fractal_noise
from roadsurf.simulation.placement import place_features
from roadsurf.simulation.route import Route, Trajectory
from roadsurf.simulation.texture import TextureField
from roadsurf.simulation.world import World

T_START_S = 2.0  # time stamp of the first frame (s); the logs start earlier, all stamps > 0
T_PAD_S = 1.5  # trajectory (and GPS/OBD logs) extend this long before and after the frames (s)


def _noise1d(t: np.ndarray, spacings: tuple[float, ...], weights: tuple[float, ...], seed: int):
    return fractal_noise(t, np.full_like(t, 0.5), spacings, weights, seed).astype(np.float64)


def _second_pass(
    t: np.ndarray,
    s: np.ndarray,
    speed: np.ndarray,
    frame_times: np.ndarray,
    half: int,
    period_s: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Arc length s(t) (m) and speed (m/s) of a revisit: from the first frame of the second
    pass (``frame_times[half]``) on, s is shifted back so that pass starts where the first
    did; between the passes (one frame period after the first pass's last frame, one before
    the second's first, so the exposure and readout see the passes' own motion) the vehicle
    goes back along the road at the constant speed that takes (its logs follow it)."""
    t_e = frame_times[half - 1] + period_s
    t_b = frame_times[half] - period_s
    shift = float(np.interp(frame_times[half], t, s) - np.interp(frame_times[0], t, s))
    s_e = float(np.interp(t_e, t, s))
    s_b = float(np.interp(t_b, t, s)) - shift
    out, v = s.copy(), speed.copy()
    late = t >= t_b
    out[late] -= shift
    gap = (t > t_e) & ~late
    out[gap] = s_e + (s_b - s_e) * (t[gap] - t_e) / (t_b - t_e)
    v[gap] = abs(s_b - s_e) / (t_b - t_e)
    return out, v


def build_world(cfg: SimConfig, seed: int, n_frames: int) -> World:
    """Draw a route, a trajectory and the defects/distractors for ``seed``."""
    cfg.check_view()  # refuse a view that reaches the horizon before drawing anything
    cfg.check_readout()
    rng = np.random.default_rng(seed)
    epsg = utm_epsg_for(cfg.origin_lat_deg, cfg.origin_lon_deg)
    en = utm_from_lla(cfg.origin_lat_deg, cfg.origin_lon_deg, epsg)[0]
    e0, n0 = float(np.round(en[0])), float(np.round(en[1]))

    # Timing and trajectory.
    fps = cfg.fps
    jitter = rng.uniform(-0.0003, 0.0003, n_frames)  # trigger jitter (s)
    jitter[0] = 0.0
    frame_times = T_START_S + np.arange(n_frames) / fps + jitter
    half = n_frames // 2
    if cfg.revisit_after_s > 0:
        if half < 2:
            raise ConfigError(f"simulator: a revisit needs at least 4 frames, got {n_frames}")
        if cfg.revisit_after_s <= 2.0 / fps:  # the way back must fit between two exposures
            raise ConfigError(
                f"simulator: revisit_after_s = {cfg.revisit_after_s:g} s is too short for a way "
                f"back between the passes; use more than two frame periods ({2.0 / fps:g} s)"
            )
        frame_times[half:] += cfg.revisit_after_s
    dt = 0.005
    t = np.arange(T_START_S - T_PAD_S, frame_times[-1] + T_PAD_S + dt, dt)
    seeds = rng.integers(0, 2**31, size=8)
    speed = cfg.speed_mps * (1.0 + cfg.speed_var * _noise1d(t, (2.5,), (1.0,), int(seeds[0])))
    s = 3.0 + np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt)])
    if cfg.revisit_after_s > 0:
        s, speed = _second_pass(t, s, speed, frame_times, half, 1.0 / fps)
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
        float(s.max()) + 5.0,
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
    place_features(world, rng)
    return world
