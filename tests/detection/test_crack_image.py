"""Cracks the 3D tests cannot judge, decided by the images (detection.crackimage, crackaperture)."""

import math

import numpy as np
import pytest

from roadsurf.core.camera import Camera
from roadsurf.detection.config import CrackConfig, DetectionConfig
from roadsurf.detection.crackaperture import across_parallax
from roadsurf.detection.crackdepth import PairView
from roadsurf.detection.crackimage import aperture_blind, image_consistent, readings_disagree
from roadsurf.detection.crackmap import crack_defects

CFG = CrackConfig()


def test_consistent_readings_rarely_disagree():
    """k readings of one common depth with their own errors: Q ~ χ²(k - 1), so 'disagree'
    fires at about the one-sided 3σ level (0.135 %)."""
    rng = np.random.default_rng(0)
    hits = 0
    n = 3000
    for _ in range(n):
        k = int(rng.integers(3, 10))
        se = rng.uniform(0.2e-3, 1.5e-3, k)
        hits += readings_disagree(0.001 + rng.normal(0, se), se, CFG)[0]
    assert hits / n < 0.005


def test_readings_that_contradict_each_other_disagree():
    """Two pairs 2.5 mm below, two 2.5 mm above the road, each ± 0.5 mm: no common depth."""
    se = np.full(4, 0.5e-3)
    dis, ratio = readings_disagree(np.array([2.5, 2.3, -2.5, -2.4]) * 1e-3, se, CFG)
    assert dis and ratio > 10
    # fewer than 3 readings: no verdict
    assert readings_disagree(np.array([3e-3, -3e-3]), se[:2], CFG) == (
        False,
        pytest.approx(math.nan, nan_ok=True),
    )


def test_aperture_and_image_consistency():
    assert aperture_blind(np.array([0.1, 0.2, 0.6]), CFG)
    assert not aperture_blind(np.array([0.4, 0.5, np.nan]), CFG)
    assert not aperture_blind(np.array([np.nan]), CFG)
    assert image_consistent(3, 4, CFG) and not image_consistent(2, 2, CFG)
    assert not image_consistent(3, 8, CFG)  # seen in 3 of 8 pairs covering it


def _view(pitch_deg: float = 0.0) -> tuple[PairView, np.ndarray]:
    """A camera 1 m above the road moving 0.3 m along its image's -v direction (forward), and
    the road plane in camera a."""
    cam = Camera(640, 480, 500.0, 500.0, 320.0, 240.0, 1.0, 10.0)
    c, s = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    # camera a: z down to the road tilted forward by pitch about the x axis
    n = np.array([0.0, -s, c])  # road normal (towards the road) in camera a
    plane = np.array([0.0, s / c, 1.0 / c])  # Z = p0 X + p1 Y + p2: n·X = 1
    fwd = np.array([0.0, -c, -s])  # forward along the road, in camera a
    assert abs(n @ fwd) < 1e-12
    view = PairView(np.zeros((480, 640), np.uint8), cam, np.eye(3), -0.3 * fwd)
    return view, plane


@pytest.mark.parametrize("pitch", [0.0, 45.0])
def test_parallax_runs_with_the_travel(pitch):
    """A line along the travel (image column) sees no parallax across it; one across the
    travel (image row) sees all of it; both tilts."""
    view, plane = _view(pitch)
    v = np.arange(300, 360, dtype=float)
    along = np.c_[np.full_like(v, 320.0), v]
    across = np.c_[v + 100, np.full_like(v, 330.0)]
    s_al, j_al = across_parallax(along, view, plane)
    s_ac, j_ac = across_parallax(across, view, plane)
    assert s_al < 0.05 and s_ac > 0.95
    assert j_ac > 10 * j_al


def _pair(k: int, mean_m: float, share: float, dense_mean_m: float | None = None):
    """Pair ``k`` holding one crack piece 0.4 m long at the same place: 10 sparse points
    reading ``mean_m`` ± 1 mm (σ 1 mm each: SE 0.32 mm), optionally a dense reading."""
    from roadsurf.detection.cracks import PairCracks
    from roadsurf.detection.pairs import PairDefects

    x = np.linspace(-0.2, 0.2, 40)
    xyz = np.c_[x, np.zeros_like(x), np.full_like(x, 1.0)]
    a = np.array
    dn = dense_mean_m is not None
    c = PairCracks(
        xyz, np.zeros(len(x), int), a([0.005]), a([10 * mean_m]), a([10]),
        a([10 if mean_m > 0 else 0]), a([10 * 1e-6]), a([max(mean_m, 0.0)]),
        dense_sum_m=a([10 * dense_mean_m if dn else 0.0]), dense_n=a([10.0 if dn else 0.0]),
        dense_below=a([10.0 if dn and dense_mean_m > 0 else 0.0]),
        dense_var_m2=a([10 * 1e-6 if dn else 0.0]),
        across_share=a([share]),
    )  # fmt: skip
    z = np.zeros(3)
    return PairDefects(k, f"{k:06d}.png", z.astype(bool), z.astype(bool), z, 0.008, 0.001, 0.0,
                       0.0, cracks=c)  # fmt: skip


def _defects(pairs, cfg=None):
    from roadsurf.detection.mapframe import MapFrame
    from roadsurf.mapping.types import Trajectory
    from tests.detection.synthetic import poses

    n = len(pairs)
    T = np.repeat(poses(1), n, axis=0)  # every frame a at the same place: pieces coincide
    names = [f"{k:06d}.png" for k in range(n)]
    traj = Trajectory(names, np.arange(n), np.zeros(n), T, ["gps"] * n, None)
    per = dict(enumerate(pairs))
    return crack_defects(
        cfg or DetectionConfig(), per, traj, {f: i for i, f in enumerate(names)},
        MapFrame.create(None), {}, [],
    )  # fmt: skip


def test_crack_whose_readings_contradict_is_kept_on_the_images_without_depth():
    """Four pairs see the line; their depth readings contradict each other (2 mm below, 2 mm
    above the road, ± 0.3 mm): the 3D test is blind there, the images decide, depth NaN."""
    pairs = [_pair(k, m, 0.5) for k, m in enumerate([2e-3, -2e-3, 2e-3, -2e-3])]
    out = _defects(pairs)
    assert [d.type for d in out] == ["crack"]
    d = out[0]
    assert d.measured_on == "image" and math.isnan(d.max_depth_m) and math.isnan(d.mean_depth_m)
    assert d.length_m > 0.3 and 0 < d.confidence <= 0.5
    # off: the pooled 3D test alone (z ≈ 0) vetoes it
    off = DetectionConfig(crack=CrackConfig(image_confirm=False))
    assert _defects(pairs, off) == []


def test_road_level_line_across_the_travel_is_not_kept():
    """Consistent readings at road level, the line across the parallax: the 3D test sees it
    and says no, whatever the images."""
    rng = np.random.default_rng(1)
    pairs = [_pair(k, float(rng.normal(0, 0.3e-3)), 0.9, 0.0) for k in range(5)]
    assert _defects(pairs) == []


def test_line_seen_by_too_few_pairs_is_not_kept():
    """Along the travel (blind), but extracted by two pairs only."""
    assert _defects([_pair(k, 0.0, 0.1) for k in range(2)]) == []
    # two pairs whose readings contradict: too few readings to call them inconsistent
    assert _defects([_pair(k, m, 0.5) for k, m in enumerate([2e-3, -2e-3])]) == []


def test_line_along_the_travel_is_decided_by_the_images():
    """Along the travel (aperture-blind) three consistent pairs' line is kept: there a road-level
    line cannot be told from a crack by the 3D test (the documented limit)."""
    pairs = [_pair(k, 0.0, 0.1) for k in range(3)]
    out = _defects(pairs)
    assert len(out) == 1 and out[0].measured_on == "image"
    off = DetectionConfig(crack=CrackConfig(image_confirm=False))
    assert _defects(pairs, off) == []
