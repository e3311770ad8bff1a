"""The simulated drives of the classifier benchmark (``benchmarks.classifier``).

Training drives use the default gravel texture and lighting plus other textures, suns,
exposures and greyscale; the test drives keep an unseen texture and light, and a long drive
with few defects (~5% of frames) gives the time ratio fused / physics.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from roadsurf.core.errors import RoadsurfError


@dataclass(frozen=True)
class DriveSpec:
    """One simulated drive of the benchmark."""

    name: str
    scenario: str
    seed: int
    n_frames: int
    overrides: dict[str, Any] = field(default_factory=dict)


# defects and distractors of the long training drives (plus their own potholes)
_LONG_LAYOUT: dict[str, Any] = {
    "n_cracks": 1,
    "n_ruts": 1,
    "n_lane_markings": 2,
    "n_shadows": 3,
    "n_oil_stains": 2,
}

# Training: the default gravel texture and lighting, several seeds and layouts.
TRAIN_DRIVES = (
    DriveSpec("train_a", "potholes", 1101, 60),
    DriveSpec("train_b", "potholes", 1102, 60, {"sun_azimuth_deg": 60.0, "n_lane_markings": 2}),
    DriveSpec("train_c", "flat", 1103, 40, {"n_shadows": 2, "n_lane_markings": 2}),
    # more varied training data (round 2): other photo texture, low/other sun, greyscale,
    # darker exposure, dense distractors on clear road. The test texture/lighting stay unseen.
    DriveSpec(
        "train_d",
        "potholes",
        1104,
        60,
        {
            "texture": "brick",
            "sun_azimuth_deg": 210.0,
            "sun_elevation_deg": 30.0,
            "ambient": 0.55,
            "n_shadows": 3,
            "n_oil_stains": 2,
        },
    ),
    DriveSpec(
        "train_e",
        "potholes",
        1105,
        60,
        {
            "greyscale": True,
            "exposure": 0.75,
            "sun_elevation_deg": 60.0,
            "n_lane_markings": 3,
            "n_oil_stains": 2,
        },
    ),
    DriveSpec(
        "train_f",
        "flat",
        1106,
        40,
        {
            "texture": "grass",
            "ambient": 0.6,
            "exposure": 1.15,
            "n_shadows": 4,
            "n_lane_markings": 3,
            "n_oil_stains": 3,
        },
    ),
    # round 3: long stretches of clear road (real drives are mostly clear, and a screening CNN
    # must be sure about plain road of any look), under other lights, cameras and tone; still
    # no asphalt texture and no test lighting.
    DriveSpec(
        "train_g",
        "long",
        1107,
        100,
        {
            **_LONG_LAYOUT,
            "texture": "grass",
            "sun_azimuth_deg": 20.0,
            "sun_elevation_deg": 50.0,
            "cloud_shadow": 0.4,
            "n_potholes": 2,
        },
    ),
    DriveSpec(
        "train_h",
        "potholes",
        1108,
        60,
        {
            "texture": "brick",
            "greyscale": True,
            "image_format": "png",
            "exposure": 0.6,
            "ambient": 0.8,
            "noise_sigma": 3.0,
            "cloud_shadow": 0.3,
            "n_ruts": 2,
        },
    ),
    DriveSpec(
        "train_i",
        "long",
        1109,
        100,
        {
            "texture": "gravel",
            "greyscale": True,
            "sun_azimuth_deg": 100.0,
            "sun_elevation_deg": 40.0,
            "ambient": 0.5,
            "exposure": 1.25,
            "vignetting": 0.4,
            "n_potholes": 2,
            "n_cracks": 1,
            "n_ruts": 1,
            "n_lane_markings": 3,
            "n_shadows": 3,
            "n_oil_stains": 2,
        },
    ),
    # round 4: more long stretches of road (the CNN must be sure about plain road to save
    # time), other seeds, sun positions and exposures; still no asphalt and no test lighting
    DriveSpec(
        "train_j",
        "long",
        1110,
        120,
        {**_LONG_LAYOUT, "sun_azimuth_deg": 250.0, "sun_elevation_deg": 55.0, "n_potholes": 3},
    ),
    DriveSpec(
        "train_k",
        "long",
        1111,
        120,
        {
            "texture": "brick",
            "greyscale": True,
            "exposure": 0.9,
            "ambient": 0.65,
            "sun_azimuth_deg": 160.0,
            "n_potholes": 3,
            "n_cracks": 1,
            "n_ruts": 1,
            "n_lane_markings": 1,
            "n_shadows": 2,
            "n_oil_stains": 1,
        },
    ),
    DriveSpec(
        "train_l",
        "potholes",
        1112,
        60,
        {
            "texture": "grass",
            "image_format": "png",
            "sun_elevation_deg": 25.0,
            "cloud_shadow": 0.3,
            "n_lane_markings": 2,
        },
    ),
)
# Testing: unseen seeds, another texture, other light, greyscale JPEG, more distractors.
TEST_DRIVES = (
    DriveSpec(
        "test_asphalt",
        "potholes",
        2101,
        60,
        {
            "texture": "asphalt",
            "sun_azimuth_deg": 300.0,
            "sun_elevation_deg": 35.0,
            "n_lane_markings": 2,
            "n_shadows": 3,
        },
    ),
    DriveSpec(
        "test_grey",
        "potholes",
        2102,
        60,
        {
            "greyscale": True,
            "ambient": 0.7,
            "exposure": 0.85,
            "n_lane_markings": 2,
            "n_shadows": 2,
            "n_oil_stains": 2,
        },
    ),
)
# Long drive with few defects (~5% of frames) for the time ratio.
LONG_DRIVE = DriveSpec(
    "long_few_defects",
    "long",
    2103,
    200,
    {"n_potholes": 3, "n_cracks": 1, "n_ruts": 0, "n_lane_markings": 2, "n_shadows": 2},
)


def shortened(spec: DriveSpec, n: int) -> DriveSpec:
    """``spec`` with at most ``n`` frames (``--quick``)."""
    return dataclasses.replace(spec, n_frames=min(spec.n_frames, n))


def simulate_drive(spec: DriveSpec, root: Path) -> Path:
    """Render ``spec`` into ``root/drives/<name>`` unless a finished render is there."""
    out = root / "drives" / spec.name
    if (out / "truth" / "frame_labels.csv").is_file():
        return out
    from roadsurf.simulation.scenarios import simulate

    if out.exists():
        shutil.rmtree(out)
    simulate(spec.scenario, out, seed=spec.seed, n_frames=spec.n_frames, **spec.overrides)
    return out


def require_simulator() -> None:
    """Raise a RoadsurfError naming the missing package when the simulator cannot import."""
    try:
        import roadsurf.simulation.scenarios  # noqa: F401
    except ImportError as e:
        raise RoadsurfError(f"bench classifier needs the simulator package ({e})") from e
