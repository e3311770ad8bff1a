"""Named scenarios and the ``simulate`` entry point (``roadsurf simulate``).

A scenario is a default seed, a default frame count and a set of ``SimConfig`` overrides.
``simulate(name, out, seed=None, n_frames=None, **overrides)`` renders the drive in the drive
format (camera.yaml, frames/, frames.csv, gps.csv, obd.csv) plus DRIVE/truth/.
Rendering is deterministic for a given (scenario, seed, overrides): same bytes.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm import tqdm

from roadsurf.core.atomic import write_bytes_atomic, write_json_atomic, write_text_atomic
from roadsurf.core.config import from_dict, load_yaml_config
from roadsurf.core.errors import ConfigError, RoadsurfError
from roadsurf.io import drivefolder as df
from roadsurf.io.formats import write_csv
from roadsurf.simulation.build import build_world
from roadsurf.simulation.config import SimConfig
from roadsurf.simulation.overlay import MASK_NAME, apply_overlay, write_masks
from roadsurf.simulation.placement import footprint_m
from roadsurf.simulation.render import Renderer
from roadsurf.simulation.sensors import (
    encode_image,
    form_image,
    gps_params,
    gpx_text,
    nmea_text,
    simulate_gps,
    simulate_obd,
    time_offset_s,
)
from roadsurf.simulation.truth import (
    corridor_polygon,
    write_features,
    write_frame_labels,
    write_poses,
    write_rasters,
)

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Scenario:
    description: str
    seed: int
    n_frames: int
    overrides: dict[str, Any]


SCENARIOS: dict[str, Scenario] = {
    "flat": Scenario(
        "flat road, no defects; lane marking, shadow, oil stain only",
        101,
        40,
        {"n_potholes": 0, "n_cracks": 0, "n_ruts": 0},
    ),
    "potholes": Scenario(
        "residential street with 5 potholes, 2 cracks, a rut and distractors",
        202,
        60,
        {"n_potholes": 5, "n_cracks": 2, "n_ruts": 1, "n_shadows": 2, "n_oil_stains": 1},
    ),
    "vibration": Scenario(
        "potholes under strong vibration (θ ~ 1.5°, δ_h ~ 8 mm)",
        303,
        60,
        {
            "n_potholes": 4,
            "vibration_deg": 1.5,
            "yaw_noise_deg": 0.6,
            "height_noise_m": 0.008,
            "vibration_hz": 4.0,
        },
    ),
    "rough-gps": Scenario(
        "consumer GPS (1 Hz, σ 1 m, slow bias, 2 dropouts), slower drive, other texture",
        404,
        120,
        {
            "gps_profile": "consumer",
            "gps_dropouts": 2,
            "gps_dropout_s": 2.0,
            "fps": 10.0,
            "speed_mps": 4.0,
            "n_potholes": 4,
            "texture": "asphalt",
            "sun_azimuth_deg": 250.0,
            "cloud_shadow": 0.4,
        },
    ),
    "revisit": Scenario(
        "the same lane driven twice, 20 s apart (a survey that comes back), consumer GPS",
        808,
        60,
        {
            "revisit_after_s": 20.0,
            "gps_profile": "consumer",
            "fps": 10.0,
            "speed_mps": 4.0,
            "n_potholes": 3,
            "n_cracks": 1,
            "texture": "asphalt",
        },
    ),
    "highway": Scenario(
        "highway: 25 m/s at 60 fps, lane markings, short exposure, overcast light",
        505,
        80,
        {
            "speed_mps": 25.0,
            "fps": 60.0,
            "exposure_time_s": 0.0002,
            "n_lane_markings": 3,
            "marking_style": "dashed",
            "n_potholes": 3,
            "n_cracks": 2,
            "n_ruts": 1,
            "ambient": 0.7,
            "texture": "asphalt",
            "vibration_deg": 0.4,
            "sun_elevation_deg": 60.0,
        },
    ),
    "long": Scenario(
        "600-frame drive for memory/speed benchmarks, ~5% defect frames",
        606,
        600,
        {
            "n_potholes": 8,
            "n_cracks": 3,
            "n_ruts": 1,
            "n_lane_markings": 4,
            "n_shadows": 4,
            "n_oil_stains": 3,
        },
    ),
    "varied": Scenario(
        "robustness: brick texture, low sun + clouds, lens distortion, 8-bit grey PNG, NMEA GPS",
        707,
        40,
        {
            "texture": "brick",
            "sun_elevation_deg": 25.0,
            "sun_azimuth_deg": 300.0,
            "cloud_shadow": 0.5,
            "distortion": (-0.12, 0.03, 0.0005, -0.0005, 0.0),
            "greyscale": True,
            "image_format": "png",
            "gps_format": "nmea",
            "n_potholes": 3,
            "n_cracks": 1,
            "n_ruts": 1,
            "n_shadows": 2,
            "vibration_deg": 0.8,
        },
    ),
    "tilted": Scenario(
        "the potholes street seen by a camera tilted 25° forward (mount not in camera.yaml), "
        "GPS σ 5 cm",
        202,
        60,
        {
            "n_potholes": 5,
            "n_cracks": 2,
            "n_ruts": 1,
            "n_shadows": 2,
            "n_oil_stains": 1,
            "mount_pitch_deg": 25.0,
            "gps_sigma_m": 0.05,
        },
    ),
    "dashcam": Scenario(
        "a windscreen camera: 1280x720, 30° forward, 1° roll (not in camera.yaml), a burned-in "
        "stamp and the bonnet (their mask in camera.yaml), 20 ms rolling shutter, exposure "
        "jitter, JPEG 75, consumer GPS as NMEA",
        909,
        60,
        {
            "width": 1280,
            "height": 720,
            "fx": 900.0,
            "mount_pitch_deg": 30.0,
            "mount_roll_deg": 1.0,
            "overlay_text": True,
            "hood_share": 0.12,
            "write_mask": True,
            "readout_s": 0.02,
            "exposure_var": 0.1,
            "jpeg_quality": 75,
            "gps_profile": "consumer",
            "gps_format": "nmea",
        },
    ),
    "sample": Scenario(
        "the committed data_samples/drive: 3+ potholes, crack, marking, shadow, oil stain",
        7,
        50,
        {
            "n_potholes": 4,
            "n_cracks": 1,
            "n_ruts": 0,
            "n_lane_markings": 1,
            "n_shadows": 1,
            "n_oil_stains": 1,
            "jpeg_quality": 88,
        },
    ),
}


def describe() -> dict[str, str]:
    """Scenario name -> one-line description (with its default seed and frame count)."""
    return {
        k: f"{s.description} (seed {s.seed}, {s.n_frames} frames)" for k, s in SCENARIOS.items()
    }


def make_config(name: str, config: str | Path | None = None, **overrides: Any) -> SimConfig:
    """SimConfig of scenario ``name``: its overrides, then the YAML file ``config`` (a mapping
    of SimConfig fields), then keyword ``overrides``. Unknown keys raise ConfigError."""
    if name not in SCENARIOS:
        raise ConfigError(
            f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)} (roadsurf simulate --list)"
        )
    data = dict(SCENARIOS[name].overrides)
    if config is not None:
        from_file = load_yaml_config(SimConfig, config)  # validates, naming the file
        raw = yaml.safe_load(Path(config).read_text(encoding="utf-8")) or {}
        data.update({k: getattr(from_file, k) for k in raw})
    data.update(overrides)
    cfg = from_dict(SimConfig, data, f"scenario {name!r}")
    cfg.check_view()
    cfg.check_readout()
    return cfg


def prepare_out(out: Path) -> None:
    known = {df.FRAMES_DIR, df.TRUTH_DIR, df.CAMERA_YAML, df.FRAMES_CSV, df.OBD_CSV, MASK_NAME}
    known |= set(df.GPS_FILES)
    if out.exists() and any(out.iterdir()):
        if not {p.name for p in out.iterdir()} <= known:
            raise RoadsurfError(
                f"{out}: folder exists and is not a simulated drive; refusing to overwrite. "
                "Choose an empty or new --out folder."
            )
        # A previous simulated drive: replace all of it (a stale gps.csv would win over a new
        # gps.gpx in the loader's priority order).
        for item in out.iterdir():
            if item.is_dir():
                shutil.rmtree(item)
            else:
                item.unlink()
    (out / df.FRAMES_DIR).mkdir(parents=True, exist_ok=True)
    (out / df.TRUTH_DIR).mkdir(parents=True, exist_ok=True)


def simulate(
    name: str,
    out: str | Path,
    seed: int | None = None,
    n_frames: int | None = None,
    progress: bool = True,
    config: str | Path | None = None,
    **overrides: Any,
) -> Path:
    """Render scenario ``name`` into folder ``out`` (drive format + truth/). Returns ``out``.

    ``config``: optional YAML file of SimConfig fields; ``overrides``: SimConfig fields by name
    (they win over the file, which wins over the scenario)."""
    cfg = make_config(name, config, **overrides)
    sc = SCENARIOS[name]
    seed = sc.seed if seed is None else int(seed)
    n = sc.n_frames if n_frames is None else int(n_frames)
    if n < 2:
        raise ConfigError(f"n_frames must be >= 2, got {n}")
    out = Path(out)
    prepare_out(out)
    t0 = time.perf_counter()
    world = build_world(cfg, seed, n)
    renderer = Renderer(world)
    ext = cfg.image_format
    names = [f"frame_{k:06d}.{ext}" for k in range(n)]
    poses, labels, footprints = [], [], []
    for k in tqdm(range(n), desc=f"render {name}", unit="frame", disable=not progress):
        pose = world.pose(float(world.frame_times[k]))
        fr = renderer.render(pose)
        rng = np.random.default_rng([seed, 1000 + k])
        gain = float(1.0 + cfg.exposure_var * rng.standard_normal())
        speed = float(np.interp(pose.t, world.traj.t, world.traj.speed))
        img = form_image(fr.radiance, cfg, speed, gain, rng)
        img = apply_overlay(img, cfg, float(world.frame_times[k]), speed)  # burned in: after
        # the sensor model, before encoding
        write_bytes_atomic(out / df.FRAMES_DIR / names[k], encode_image(img, cfg))
        poses.append((names[k], pose))
        labels.append((names[k], fr.defect_area_m2, fr.max_depth_m))
        footprints.append(fr.footprint)
    t_render = time.perf_counter() - t0

    _write_drive_files(world, out, names)
    truth = out / df.TRUTH_DIR
    write_poses(world, truth, poses, time_offset_s(cfg))
    write_frame_labels(truth, labels)
    write_features(world, truth)
    grid = write_rasters(world, corridor_polygon(footprints), truth)
    fw, fl = footprint_m(cfg)
    step = cfg.speed_mps / cfg.fps
    write_json_atomic(
        truth / df.TRUTH_SCENARIO_JSON,
        {
            "scenario": name,
            "seed": seed,
            "crs": world.crs,
            "n_frames": n,
            "params": dataclasses.asdict(cfg),
            "derived": {
                "origin_easting_m": world.origin_e_m,
                "origin_northing_m": world.origin_n_m,
                "render_gsd_m": world.render_gsd_m,
                "truth_gsd_m": grid.gsd_m,
                "footprint_across_m": round(fw, 4),
                "footprint_along_m": round(fl, 4),
                "nominal_overlap": round(1.0 - step / fl, 4),
                "gps": gps_params(cfg),
                "n_defects": len(world.potholes) + len(world.troughs),
                "n_distractors": len(world.distractors),
            },
        },
    )
    log.info(
        "simulated %s (seed %d): %d frames in %.1f s render (%.3f s/frame) -> %s",
        name, seed, n, t_render, t_render / n, out,
    )  # fmt: skip
    return out


def write_camera_yaml(cfg: SimConfig, out: Path) -> None:
    """out/camera.yaml of the simulated camera (the mount only with ``write_mount``, the image
    mask only with ``write_mask``) and the overlays' masks (``overlay.write_masks``)."""
    cam = cfg.camera()
    text = (
        "# written by roadsurf simulate\n"
        f"model: {cam.model}\n"
        f"width: {cam.width}\nheight: {cam.height}\n"
        f"fx: {cam.fx!r}\nfy: {cam.fy!r}\ncx: {cam.cx!r}\ncy: {cam.cy!r}\n"
        f"dist: [{', '.join(repr(k) for k in cam.dist)}]\n"
        f"height_m: {cam.height_m!r}\n"
        f"fps: {cam.fps!r}\n"
    )
    if cam.mount_deg is not None:  # only with write_mount: otherwise the pipeline estimates it
        keys = ("mount_pitch_deg", "mount_roll_deg", "mount_yaw_deg")
        text += "".join(f"{k}: {v!r}\n" for k, v in zip(keys, cam.mount_deg, strict=True))
    if cam.readout_s > 0:  # a rolling shutter (docs/formats.md)
        text += f"readout_s: {cam.readout_s!r}\n"
    if any(cfg.gps_antenna_m):  # the fixes are the antenna's (simulation.sensors)
        text += f"gps_antenna_m: [{', '.join(repr(float(v)) for v in cfg.gps_antenna_m)}]\n"
    if cfg.write_mask:  # the image mask, relative to camera.yaml's folder (docs/simulator.md)
        text += f"mask: {MASK_NAME}\n"
    write_masks(cfg, out)
    write_text_atomic(out / df.CAMERA_YAML, text)


def _write_drive_files(world, out: Path, names: list[str]) -> None:
    cfg = world.cfg
    write_camera_yaml(cfg, out)
    off = time_offset_s(cfg)
    write_csv(
        out / df.FRAMES_CSV,
        ["filename", "timestamp_s"],
        [[nm, round(float(t) + off, 6)] for nm, t in zip(names, world.frame_times, strict=True)],
    )
    rng = np.random.default_rng([world.seed, 7])
    gps = simulate_gps(world, rng)
    if cfg.gps_format == "gpx":
        write_text_atomic(out / df.GPS_GPX, gpx_text(gps, off))
    elif cfg.gps_format == "nmea":
        quality = 4 if cfg.gps_profile == "rtk" else 1  # RTK fixed / GPS fix
        write_text_atomic(out / df.GPS_NMEA, nmea_text(gps, off, quality))
    else:
        write_csv(
            out / df.GPS_CSV,
            ["timestamp_s", "lat", "lon", "alt_m", "hdop"],
            zip(gps.timestamp_s, gps.lat_deg, gps.lon_deg, gps.alt_m, gps.hdop, strict=True),
        )
    t, v = simulate_obd(world, np.random.default_rng([world.seed, 8]))
    write_csv(
        out / df.OBD_CSV, ["timestamp_s", "speed_mps"], zip(np.round(t + off, 3), v, strict=True)
    )
