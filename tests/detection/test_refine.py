"""2D + 3D refinement (Fig. 4.3): binarisation (fixed vs adaptive T_b) and CORRECT_DEFECTS."""

import dataclasses

import numpy as np

from roadsurf.detection.config import RefineConfig
from roadsurf.detection.refine import binarise, correct_defects
from tests.detection.synthetic import CAMERA, Pothole, Scene, poses, render

T0 = poses(1)[0]
FIXED = RefineConfig(binarise="fixed", fixed_threshold=90)
ADAPTIVE = RefineConfig(binarise="adaptive")


def _road_px(scene, n=2000, seed=0):
    """Pixels of flat-road points (what the plane fit calls X^rn)."""
    rng = np.random.default_rng(seed)
    px = np.column_stack(
        [rng.uniform(0, CAMERA.width - 1, n), rng.uniform(0, CAMERA.height - 1, n)]
    )
    x = (px[:, 0] - CAMERA.cx) / CAMERA.fx * CAMERA.height_m
    y = -(px[:, 1] - CAMERA.cy) / CAMERA.fy * CAMERA.height_m
    return px[scene.depth(x, y) == 0]


def _shadow_cols(scene):
    # Image columns whose ground x is inside the shadow (camera x = east for heading north).
    u = np.arange(CAMERA.width)
    x = (u - CAMERA.cx) / CAMERA.fx * CAMERA.height_m
    return x > scene.shadow_x_m


def test_adaptive_threshold_ignores_a_shadow_fixed_does_not():
    scene = Scene(shadow_x_m=0.1)
    img = render(scene, T0)
    cols = _shadow_cols(scene)
    inner = np.flatnonzero(cols)[15:]  # away from the shadow's edge
    fixed = binarise(img, FIXED)
    assert fixed[:, inner].mean() > 0.9
    for road_px in (None, _road_px(scene)):
        adaptive = binarise(img, ADAPTIVE, road_px=road_px)
        assert adaptive[:, inner].mean() < 0.05


def test_both_find_a_dark_pothole_and_ignore_a_bright_lane_marking():
    scene = Scene(potholes=[Pothole(0.0, 0.0, 0.12, 0.03, darker=0.4)], lane_x_m=-0.35)
    img = render(scene, T0)
    c = (int(CAMERA.cy), int(CAMERA.cx))
    for cfg in (FIXED, ADAPTIVE):
        dark = binarise(img, cfg, road_px=_road_px(scene))
        assert dark[c[0] - 3 : c[0] + 4, c[1] - 3 : c[1] + 4].all()
        lane_u = int(CAMERA.cx - 0.35 * CAMERA.fx)
        assert not dark[:, lane_u].any()


def test_adaptive_survives_overexposure():
    scene = Scene(potholes=[Pothole(0.0, 0.0, 0.12, 0.03, darker=0.6)])
    img = np.clip(render(scene, T0).astype(int) * 2 + 40, 0, 255).astype(np.uint8)
    c = (int(CAMERA.cy), int(CAMERA.cx))
    dark = binarise(img, ADAPTIVE, road_px=_road_px(scene))
    assert dark[c[0] - 2 : c[0] + 3, c[1] - 2 : c[1] + 3].all()
    assert not binarise(img, FIXED)[c[0] - 2 : c[0] + 3, c[1] - 2 : c[1] + 3].any()


def test_correct_defects_keeps_dark_candidates_and_grows():
    rng = np.random.default_rng(0)
    h, w = 60, 80
    dark = np.zeros((h, w), bool)
    dark[20:40, 30:50] = True
    px = np.column_stack([rng.uniform(0, w - 1, 2000), rng.uniform(0, h - 1, 2000)])
    inside = dark[np.round(px[:, 1]).astype(int), np.round(px[:, 0]).astype(int)]
    d = rng.normal(0, 0.0005, 2000)
    d[inside] = -0.006  # shallow part of a defect: below the road but under T_d
    d[np.flatnonzero(inside)[:5]] = -0.012  # a few candidates over T_d
    noise_cand = np.flatnonzero(~inside)[:3]
    d[noise_cand] = -0.011  # isolated candidates on bright road (noise)
    cand = d <= -0.008
    out = correct_defects(d, px, cand, dark, 0.008, RefineConfig())
    assert out[inside].all()  # grown to the whole dark region's points below the road
    assert not out[noise_cand].any()  # isolated bright-road candidates dropped
    # Very deep candidates need no 2D support.
    d[noise_cand[0]] = -0.05
    out = correct_defects(d, px, d <= -0.008, dark, 0.008, RefineConfig())
    assert out[noise_cand[0]]
    # Disabled growth factor: only the candidates themselves.
    cfg = dataclasses.replace(RefineConfig(), grow_depth_frac=10.0)
    assert correct_defects(d, px, d <= -0.008, dark, 0.008, cfg).sum() == 6
