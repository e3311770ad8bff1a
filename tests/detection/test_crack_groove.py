"""Crack depth from a groove model fitted to the cross-section profiles in both images
(detection.crackgroove), on two frames of the simulator's own renderer (gravel texture, sensor
noise, motion blur, a 5 % exposure change, JPEG 90): issue 29, D007 of the simulated potholes
drive, 3.4 mm deep and 5.7 mm wide at 1.8 mm pixels, was read 0.28 mm deep by the LK tracks of
its centre line (z 1.3; the window's gravel dominates its shift) and missed."""

from __future__ import annotations

import math

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackdepth import PairView
from roadsurf.detection.crackgroove import groove_crack_depth
from roadsurf.detection.crackmap import crack_evidence
from roadsurf.detection.cracks import detect_pair_cracks
from roadsurf.simulation.build import build_world
from roadsurf.simulation.defects import Trough
from roadsurf.simulation.render import Renderer
from roadsurf.simulation.scenarios import make_config
from roadsurf.simulation.sensors import form_image
from roadsurf.simulation.shapes import Polyline

W, H, F, HEIGHT = 480, 360, 600.0, 1.1  # 1.8 mm pixels, like the simulated drives' 640 px camera
CAM = Camera(
    width=W, height=H, fx=F, fy=F, cx=(W - 1) / 2, cy=(H - 1) / 2, height_m=HEIGHT, fps=15.0
)
CFG = CrackConfig()
QUIET = {"n_potholes": 0, "n_cracks": 0, "n_ruts": 0, "n_lane_markings": 0, "n_shadows": 0}
STILL = {"vibration_deg": 0.0, "height_noise_m": 0.0, "grade": 0.0, "cross_slope": 0.0}
STILL |= {"undulation_m": 0.0, "yaw_noise_deg": 0.0, "lateral_wander_m": 0.0, "speed_var": 0.0}


def _pair(depth_m: float, seed: int, angle_deg: float = 65.0, width_m: float = 0.0057):
    """Two rendered frames 0.4 m apart with one crack at ``angle_deg`` to the direction of
    travel, in the part of image a that image b sees: (centre line in a, image a, view, road
    plane in camera a, the world's camera-a pose)."""
    cfg = make_config(
        "flat", width=W, height=H, fx=F, camera_height_m=HEIGHT, fps=15.0, speed_mps=6.0,
        n_oil_stains=0, route_curve_amp_deg=0.0, **QUIET, **STILL,
    )  # fmt: skip
    world = build_world(cfg, seed, 2)
    pa, pb = (world.pose(float(t)) for t in world.frame_times[:2])
    fwd = (pb.C[:2] - pa.C[:2]) / np.linalg.norm(pb.C[:2] - pa.C[:2])
    a = math.radians(angle_deg)
    along = math.cos(a) * fwd + math.sin(a) * np.array([-fwd[1], fwd[0]])
    mid = pa.C[:2] + 0.2 * fwd
    ends = np.array([mid - 0.25 * along, mid + 0.25 * along])
    line = Polyline(tuple(map(tuple, ends.tolist())), width_m)
    world.troughs.append(Trough("crack", line, depth_m, 0.0))
    rnd, rng = Renderer(world), np.random.default_rng(seed)
    imgs = []
    for k, p in enumerate((pa, pb)):
        img = form_image(rnd.render(p).radiance, cfg, cfg.speed_mps, 1.0 + 0.05 * k, rng)
        img = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1]
        imgs.append(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))
    z0 = float(world.base(np.array(pa.C[0]), np.array(pa.C[1])))
    ground = np.array([[pa.C[0] + dx, pa.C[1] + dy, z0] for dx, dy in ((0, 0), (1, 0), (0, 1))])
    g = (ground - pa.C) @ pa.R  # camera a (X_cam = R^T (X_world - C))
    plane = np.linalg.solve(np.c_[g[:, :2], np.ones(3)], g[:, 2])
    e = (np.c_[ends, np.full(2, z0)] - pa.C) @ pa.R
    px = (e @ CAM.K.T)[:, :2] / e[:, 2:3]
    centre = np.zeros((H, W), np.uint8)
    cv2.line(centre, *(tuple(int(round(c)) for c in p) for p in px), 1, 1)
    view = PairView(imgs[1], CAM, pb.R.T @ pa.R, pb.R.T @ (pa.C - pb.C))
    return centre.astype(bool), imgs[0], view, plane


def _z(m) -> float:
    return float(m.sum_m / math.sqrt(m.var_m2))


W_PX = 0.9 * 0.0057 * F / HEIGHT  # the 2D detector's equivalent width of the rendered band


SEEDS = range(6)


def test_shallow_crack_with_a_wide_dark_band_reads_significant():
    """Over six renders (texture, noise) the groove's z averages above the threshold (20
    renders: mean 5.4, σ 1.6; the LK tracks 2.3) and its depth is a real share of 3.4 mm."""
    zs, depths = [], []
    for seed in SEEDS:
        line, ga, view, plane = _pair(0.0034, seed)
        m = groove_crack_depth(line, W_PX, ga, view, plane, CFG)
        assert m is not None
        zs.append(_z(m))
        depths.append(float(m.depth_m.mean()))
    assert np.mean(zs) >= CFG.z_k, zs
    assert 0.0005 < np.mean(depths) <= 0.0034 + 0.001, depths


def test_dark_line_at_road_level_reads_no_depth():
    """The same dark band without a groove: z about standard normal (20 renders: mean -0.06,
    σ 1.1), never beyond the threshold here."""
    zs = []
    for seed in SEEDS:
        line, ga, view, plane = _pair(0.0, seed)
        m = groove_crack_depth(line, W_PX, ga, view, plane, CFG)
        assert m is not None
        assert abs(float(m.depth_m.mean())) < 0.001
        zs.append(_z(m))
    assert max(abs(z) for z in zs) < CFG.z_k, zs
    assert abs(np.mean(zs)) < 1.0, zs


def test_crack_along_the_direction_of_travel_gives_no_reading():
    """The parallax runs along it: nothing across to read (not faked)."""
    line, ga, view, plane = _pair(0.0034, 0, angle_deg=5.0)
    assert groove_crack_depth(line, W_PX, ga, view, plane, CFG) is None


def test_one_pair_confirms_the_crack_the_lk_tracks_missed():
    """The whole pair: 2D detector, sparse points (at road level on the groove, as the 21 px
    matcher reads it) and the dense reading pooled as the map does (``crackmap``)."""
    line, ga, view, plane = _pair(0.0034, 1)
    rng = np.random.default_rng(5)
    px = np.c_[rng.uniform(0, W - 1, 800), rng.uniform(0, H * 0.45, 800)]
    ray = np.c_[(px - [CAM.cx, CAM.cy]) / F, np.ones(len(px))]
    P = ray * (plane[2] / (ray[:, 2] - ray[:, :2] @ plane[:2]))[:, None]
    dist = rng.normal(0.0, 0.001, len(px))
    P[:, 2] -= dist
    c = detect_pair_cracks(
        ga, px, P, dist, np.ones(len(px), bool), 0.001, HEIGHT / F, CFG, view, CAM
    )
    assert len(c.width_m) >= 1
    j = int(np.argmax(c.dense_n))
    wd = wsum = 0.0
    for S, n, V in ((c.sum_depth_m[j], c.n_points[j], c.var_m2[j]),
                    (c.dense_sum_m[j], c.dense_n[j], c.dense_var_m2[j])):  # fmt: skip
        if n > 0 and V > 0:
            wd, wsum = wd + S * n / V, wsum + n * n / V
    ok, z = crack_evidence(
        wd / wsum, int(c.n_points[j] + c.dense_n[j]), int(c.n_below[j] + c.dense_below[j]),
        1.0 / wsum, CFG,
    )  # fmt: skip
    assert ok, (z, c.dense_sum_m[j] / max(c.dense_n[j], 1))


NARROW_M = 0.003  # 1.5 px at 1.8 mm pixels, as a tilted camera's far field sees a 4 mm crack


def test_crack_a_pixel_and_a_half_wide_reads_significant():
    """A 3 mm wide, 4.5 mm deep crack 30° off the travel is 1.5 px wide here, like the tilted
    25° drive's 4 mm D008 in its far field. Fitted per profile, its depth drowned in noise
    (these 4 renders: z 2.0-3.4, mean 2.5; depth 0.68 mm); one depth, road shift, gain and
    offset per block read it (z 4.0-5.1, mean 4.4; 1.5 mm). A road-level dark line of the
    same width still reads no depth."""
    w_px = 0.9 * NARROW_M * F / HEIGHT
    zs, depths, flat = [], [], []
    for seed in range(4):
        line, ga, view, plane = _pair(0.0045, seed, angle_deg=30.0, width_m=NARROW_M)
        m = groove_crack_depth(line, w_px, ga, view, plane, CFG)
        assert m is not None
        zs.append(_z(m))
        depths.append(float(m.depth_m.mean()))
        line, ga, view, plane = _pair(0.0, seed, angle_deg=30.0, width_m=NARROW_M)
        m0 = groove_crack_depth(line, w_px, ga, view, plane, CFG)
        assert m0 is not None
        flat.append(_z(m0))
    assert np.mean(zs) >= CFG.z_k + 0.5, zs
    assert np.mean(depths) >= 0.0009, depths
    assert max(abs(z) for z in flat) < CFG.z_k, flat
