"""A two-frame photo pair of a pothole with a sideways baseline and no GPS (issue 29).

Real pothole photo sets (Fan et al.'s stereo pothole datasets) are pairs of one tilted camera
moved across its image rows, not along the road: the second frame is the first one's camera
moved ``baseline_m`` along its own x axis, as a stereo rig's right camera is. The drive has
two frames and ``camera.yaml`` only (no gps.csv, no obd.csv, no mount unless asked): the
pipeline must estimate the tilt from the one pair and write a local metric frame.

Truth: ``truth/height.tif`` and ``truth/residual.tif`` over both footprints (UTM, as the
drives'), ``truth/defects.geojson`` and ``truth/stereo_pair.json`` (both cameras' world_from_cam
in local metres, the UTM origin, the deepest defect point each frame sees), which
``roadsurf.evaluation.pair`` reads.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import write_bytes_atomic, write_json_atomic
from roadsurf.core.errors import ConfigError
from roadsurf.io import drivefolder as df
from roadsurf.io.formats import write_csv
from roadsurf.simulation.build import build_world
from roadsurf.simulation.overlay import apply_overlay
from roadsurf.simulation.placement import footprint_offset_m
from roadsurf.simulation.render import Renderer
from roadsurf.simulation.route import Pose
from roadsurf.simulation.scenarios import make_config, prepare_out, write_camera_yaml
from roadsurf.simulation.sensors import encode_image, form_image
from roadsurf.simulation.truth import corridor_polygon, write_features, write_rasters

log = logging.getLogger(__name__)

# A photo pair: a short slow "drive" from which the frame seeing most pothole is taken.
PAIR_DEFAULTS: dict[str, Any] = {
    "width": 960,  # image width (px); Fan et al.'s frames are 1720 x 1030
    "height": 576,  # image height (px)
    "fx": 780.0,  # focal length (px): the same field of view as fx 1400 at 1720 px
    "camera_height_m": 0.5,  # camera above the road (m), as in the real photo sets
    "mount_pitch_deg": 45.0,  # tilted forward from nadir (deg)
    "n_potholes": 6,  # potholes along the search drive (-)
    "n_cracks": 0,
    "n_lane_markings": 0,
    "n_shadows": 0,
    "n_oil_stains": 0,
    "speed_mps": 1.0,  # search drive: a frame every 0.5 m (m/s at fps 2)
    "fps": 2.0,
    "image_format": "png",
}
DEFAULT_SEED = 7  # the search drive's seed when none is given
SEARCH_FRAMES = 30  # frames of the search drive: its route and potholes (-)


def _frame_pose(p: Pose, shift_m: np.ndarray, dt: float) -> Pose:
    return Pose(p.t + dt, p.C + shift_m, p.R.copy(), p.heading_deg, p.roll_rad, p.pitch_rad)


def _pose_viewing_a_pothole(world: Any, cfg: Any) -> Pose:
    """The pose along the search drive whose footprint centre lies nearest the centre of the
    largest pothole that fits in half the footprint's width."""
    right, ahead, across = footprint_offset_m(cfg)
    fits = [q for q in world.potholes if q.shape.r_max <= 0.25 * across] or list(world.potholes)
    if not fits:
        raise ConfigError("the search drive has no pothole")
    target = max(fits, key=lambda q: q.shape.r_max)
    c = np.array([target.shape.cx, target.shape.cy])
    best: tuple[float, Pose] | None = None
    for t in np.linspace(world.frame_times[0], world.frame_times[-1], 600):
        p = world.pose(float(t))
        h = np.radians(p.heading_deg)  # grid heading, clockwise from north
        fwd, rgt = np.array([np.sin(h), np.cos(h)]), np.array([np.cos(h), -np.sin(h)])
        d = float(np.linalg.norm(p.C[:2] + right * rgt + ahead * fwd - c))
        if best is None or d < best[0]:
            best = (d, p)
    if best is None:
        raise ConfigError("the search drive has no frame times")
    return best[1]


def simulate_stereo_pair(
    out: str | Path,
    *,
    baseline_m: float = 0.12,
    seed: int = DEFAULT_SEED,
    progress: bool = False,
    **overrides: Any,
) -> Path:
    """Render the pair into ``out`` (drive format without GPS, plus truth/). ``overrides``:
    SimConfig fields over ``PAIR_DEFAULTS`` (e.g. mount_pitch_deg, texture). Returns ``out``."""
    if not 0.01 <= baseline_m <= 1.0:
        raise ConfigError(f"stereo baseline_m must be within [0.01, 1] m, got {baseline_m}")
    params = dict(PAIR_DEFAULTS, **overrides)
    cfg = make_config("potholes", None, **params)
    out = Path(out)
    prepare_out(out)
    world = build_world(cfg, seed, SEARCH_FRAMES)
    p0 = _pose_viewing_a_pothole(world, cfg)
    renderer = Renderer(world)
    fr0 = renderer.render(p0)
    if fr0.defect_area_m2 <= 0.0:
        raise ConfigError(f"no pothole in view for seed {seed}: try another seed")
    p1 = _frame_pose(p0, baseline_m * p0.R[:, 0], 0.5)  # the camera's own x: a stereo baseline
    fr1 = renderer.render(p1)
    names = [f"{k:06d}.{cfg.image_format}" for k in range(2)]
    for k, fr in enumerate((fr0, fr1)):
        img = form_image(fr.radiance, cfg, 0.0, 1.0, np.random.default_rng([seed, 500 + k]))
        img = apply_overlay(img, cfg, 0.5 * k, 0.0)  # the frames' times, a standing camera
        write_bytes_atomic(out / df.FRAMES_DIR / names[k], encode_image(img, cfg))
    write_camera_yaml(cfg, out)
    write_csv(out / df.FRAMES_CSV, ["filename", "timestamp_s"], [[names[0], 0.0], [names[1], 0.5]])
    truth = out / df.TRUTH_DIR
    write_features(world, truth)
    write_rasters(world, corridor_polygon([fr0.footprint, fr1.footprint]), truth)

    def wfc(p: Pose) -> list[list[float]]:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = p.R, p.C
        return T.tolist()

    write_json_atomic(
        truth / df.TRUTH_STEREO_PAIR_JSON,
        {
            "frames": names,
            "baseline_m": baseline_m,
            "seed": seed,
            "crs": world.crs,
            "origin_e_m": world.origin_e_m,
            "origin_n_m": world.origin_n_m,
            "world_from_cam": [wfc(p0), wfc(p1)],
            "max_depth_in_view_m": [fr0.max_depth_m, fr1.max_depth_m],
            "defect_area_in_view_m2": [fr0.defect_area_m2, fr1.defect_area_m2],
            "params": dataclasses.asdict(cfg),
        },
    )
    log.info(
        "stereo pair (seed %d, baseline %.2f m, pitch %.0f deg): deepest point in view %.1f mm -> %s",
        seed, baseline_m, cfg.mount_pitch_deg, 1e3 * fr0.max_depth_m, out,
    )  # fmt: skip
    return out
