"""The road's grade from the GPS heights (mapping.grade) and the tilt prior's axis it gives."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roadsurf.core.geometry import vehicle_from_cam_rotation
from roadsurf.mapping.grade import (
    _typical_mass,
    _window_holding,
    road_grade,
    up_axes_in_cam,
    variance_factor,
)
from roadsurf.mapping.pose_gps import GpsFixes

PRIOR = math.atan(0.02)  # MappingConfig.grade_sigma_pct


def _fixes(slope: float, length_m: float, sigma_v: float, seed: int, hz: float = 10.0):
    """Fixes along a straight road heading north-east at 6 m/s, heights on ``slope``."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, length_m / 6.0, 1.0 / hz)
    s = 6.0 * t
    e, n = s * math.sin(math.radians(40)), s * math.cos(math.radians(40))
    z = slope * s + rng.normal(0, sigma_v, len(t))
    g = GpsFixes(
        t_s=t,
        enu_m=np.column_stack([e, n, z]),
        sigma_m=np.full(len(t), sigma_v / 2.0),
        has_alt=np.ones(len(t), bool),
        orig_index=np.arange(len(t)),
    )
    return t, g


@pytest.mark.parametrize("slope", [0.0, 0.01, -0.03])
def test_an_rtk_grade_is_recovered(slope: float) -> None:
    t, g = _fixes(slope, 60.0, 0.05, seed=1)
    gr = road_grade(t, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    mid = slice(len(t) // 4, 3 * len(t) // 4)
    err = np.degrees(gr.grade_rad[mid]) - math.degrees(math.atan(slope))
    assert np.max(np.abs(err)) < 0.15  # RTK heights over ±10 m: ~0.05° standard error
    assert gr.shrink[mid].min() > 0.95
    assert np.all(np.degrees(gr.sigma_rad[mid]) < 0.1)


def _consumer(slope: float, length_m: float, seed: int, dropouts: int = 0):
    """The simulator's consumer receiver (simulation.sensors): 1 Hz at 4 m/s, white height
    noise 1.5 m, a random-walk wander of 1.5 m per √60 s, HDOP 1.6 (stated σ 0.8 m, vertical
    1.6 m), ``dropouts`` outages of 2 s; frames at 10 Hz."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, length_m / 4.0, 1.0)
    s = 4.0 * t
    e, n = s * math.sin(math.radians(40)), s * math.cos(math.radians(40))
    wander = rng.normal(0, 0.75) + np.cumsum(rng.normal(0, 1.5 / math.sqrt(60), len(t)))
    z = slope * s + wander + rng.normal(0, 1.5, len(t))
    keep = np.ones(len(t), bool)
    for _ in range(dropouts):
        t0 = rng.uniform(0, t[-1] - 2.0)
        keep &= ~((t >= t0) & (t < t0 + 2.0))
    g = GpsFixes(
        t_s=t[keep],
        enu_m=np.column_stack([e, n, z])[keep],
        sigma_m=np.full(int(keep.sum()), 0.8),
        has_alt=np.ones(int(keep.sum()), bool),
        orig_index=np.arange(int(keep.sum())),
    )
    return np.arange(0.0, t[-1], 0.1 if length_m < 100 else 0.5), g


@pytest.mark.parametrize("seed", range(8))
def test_consumer_heights_on_a_short_drive_leave_the_road_level(seed: int) -> None:
    """rough-gps's receiver over 60 m (~12 fixes): no window resolves a 0.6° grade (the whole
    track's se ~2°); the per-frame 10 m fits had read ±1-3° (se ~8°, shrunk against 3°) and
    tipped each frame's tilt prior differently (rough-gps bundle 6.7 -> 12.1 mm)."""
    t, g = _consumer(0.0105, 60.0, seed, dropouts=2)
    gr = road_grade(t, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    assert np.max(np.abs(np.degrees(gr.grade_rad))) < 0.5


@pytest.mark.parametrize("seed", range(3))
def test_a_long_consumer_drive_widens_the_window_to_its_grade(seed: int) -> None:
    """Over 600 m the same receiver resolves a 2 % grade (1.15°): the window widens to
    ~100-300 m, where white noise and wander leave ~0.3-0.5°; the 10 m fits read ±3°."""
    t, g = _consumer(0.02, 600.0, seed)
    gr = road_grade(t, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    est = np.degrees(gr.grade_rad)
    # the widened window's se is ~σ_γ / 2 = 0.57° and the shrink keeps >= 80 % (bias <= 0.23°)
    assert abs(np.median(est) - math.degrees(math.atan(0.02))) < 0.8
    assert np.max(np.abs(np.diff(est))) < 0.05  # slowly varying, no frame tipped on its own
    assert np.median(gr.shrink) > 2.0 / 3.0


def _pessimistic_hdop_fixes(t: np.ndarray, s: np.ndarray, z: np.ndarray) -> GpsFixes:
    """Fixes along a straight track (distance ``s`` m, heights ``z`` m) whose HDOP states 0.35 m
    horizontal: 0.7 m vertical at the default factor, far more than RTK heights scatter."""
    return GpsFixes(
        t_s=t,
        enu_m=np.column_stack([s * 0.6, s * 0.8, z]),
        sigma_m=np.full(len(t), 0.35),
        has_alt=np.ones(len(t), bool),
        orig_index=np.arange(len(t)),
    )


@pytest.mark.parametrize("seed", range(4))
def test_rtk_heights_with_a_pessimistic_hdop_keep_the_grade(seed: int) -> None:
    """The tilted drive's receiver: 5 Hz at 6 m/s over 40 m, heights scatter 7.5 cm while HDOP
    0.7 × 0.5 m states 0.7 m vertical: the fixes' own scatter tightens the se and the 1 %
    grade (0.57°) is kept to within 0.2° (the map's pitch: 0.57° is 15 mm at 1.5 m)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 40.0 / 6.0, 0.2)
    s = 6.0 * t
    z = 0.01 * s + rng.normal(0, 0.075, len(t)) + np.cumsum(rng.normal(0, 0.01 / 8, len(t)))
    g = _pessimistic_hdop_fixes(t, s, z)
    tf = np.arange(0.0, t[-1], 0.1)
    gr = road_grade(tf, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    err = np.degrees(gr.grade_rad) - math.degrees(math.atan(0.01))
    assert np.max(np.abs(err)) < 0.2


def _rtk_short_drive(seed: int, slope: float = 0.01):
    """benchmarks.variation's mount15_r0 drive (the tilted scenario, 36 frames): RTK at 5 Hz
    (heights 7.5 cm white, 1 cm/√60 s wander), HDOP 0.7-0.9 × 0.5 m stated, 6.3 m/s; the frames
    (15 fps) the middle 2.3 s (15 m) of 5 s of fixes, the fixes beyond them with the σ that
    mapping.pose_gps gives them (hypot(σ, ½ · 3 m/s² · Δt²), Δt the time outside the frames)."""
    rng = np.random.default_rng(seed)
    tg = np.arange(0.6, 5.61, 0.2)
    tf = np.arange(2.0, 4.34, 1.0 / 15.0)
    s = 6.3 * tg
    walk = np.cumsum(rng.normal(0, 0.01 / math.sqrt(60.0) * math.sqrt(0.2), len(tg)))
    z = slope * s + rng.normal(0, 0.075, len(tg)) + walk
    hdop = np.round(0.7 * (1 + 0.15 * np.abs(rng.standard_normal(len(tg)))), 1)
    outside = np.maximum(np.maximum(tf[0] - tg, tg - tf[-1]), 0.0)
    g = GpsFixes(
        t_s=tg,
        enu_m=np.column_stack([np.zeros(len(tg)), -s, z]),
        sigma_m=np.hypot(0.5 * hdop, 1.5 * outside**2),
        has_alt=np.ones(len(tg), bool),
        orig_index=np.arange(len(tg)),
    )
    return tf, g


@pytest.mark.parametrize("seed", range(6))
def test_a_short_rtk_drive_with_a_pessimistic_hdop_keeps_its_grade(seed: int) -> None:
    """mount15_r0's receiver: heights scatter 7.5 cm, HDOP states 0.8 m. The stated σ pooled
    arithmetically as 4 residuals held the variance factor at ~0.15 (its 1/100 read from ~24
    residuals): se 0.88° over the whole track, shrink 0.63 < 2/3 and the 1 % grade dropped at
    every seed (the estimated mount is relative to the road: the map's pitch then lost 0.5°,
    mount15_r0's in-defect 1.55 -> 2.00 mm). Pooled in its log the factor follows the scatter."""
    tf, g = _rtk_short_drive(seed)
    gr = road_grade(tf, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    err = np.degrees(gr.grade_rad) - math.degrees(math.atan(0.01))
    assert np.all(gr.shrink > 2.0 / 3.0)
    assert np.max(np.abs(err)) < 0.35  # 200 seeds: median 0.12°, 95 % 0.30°


def test_the_variance_factor_follows_the_scatter_in_its_log() -> None:
    """The stated σ weighs as 4 residuals on the log of the factor: 24 residuals 10× tighter
    than stated (RTK under HDOP × 0.5 m) give a factor near their 1/100, not the arithmetic
    pool's (4 + 24/100) / 28 = 0.15; scatter as stated gives ~1 (the Laplace mean's few %);
    few residuals move it little; no residuals leave the stated σ."""
    assert variance_factor(0.01, 24.0) < 0.04
    assert variance_factor(1.0, 24.0) == pytest.approx(1.0, abs=0.05)
    assert 0.5 < variance_factor(0.01, 2.0) < 1.0
    assert variance_factor(4.0, 100.0) == pytest.approx(4.0, rel=0.1)
    assert variance_factor(0.0, 10.0) == 1.0 and variance_factor(1.0, 0.0) == 1.0
    f = [variance_factor(c, 12.0) for c in (0.01, 0.1, 1.0, 10.0)]
    assert all(a < b for a, b in zip(f, f[1:], strict=False))


def test_the_first_window_holds_as_many_fixes_at_the_track_ends() -> None:
    """At a track's end a 10 m kernel keeps half its fixes: the first rung widens to the
    window that holds the kernel mass it holds mid-track (~2x at the very end), and only there."""
    ds = np.arange(0.0, 200.0, 1.0)
    mass = math.sqrt(2.0 * math.pi) * 10.0  # a 10 m kernel over one fix a metre
    assert _window_holding(ds - 100.0, mass, 10.0, 400.0) == pytest.approx(10.0, rel=1e-3)
    end = _window_holding(ds, mass, 10.0, 400.0)
    assert 1.8 < end / 10.0 < 2.2
    assert _window_holding(ds - 5.0, mass, 10.0, 400.0) < end  # widening fades inward


@pytest.mark.parametrize("seed", range(4))
def test_the_grade_at_a_track_end_is_as_good_as_mid_track(seed: int) -> None:
    """RTK heights (7.5 cm) at 5 Hz over 40 m, frames from the first fix: the first frames'
    one-sided 10 m kernels held half the fixes (se 0.5° against 0.2° mid-track) and read the
    1 % grade up to 0.4° off over 60 seeds; widened to the same kernel mass, within 0.2°."""
    rng = np.random.default_rng(100 + seed)
    t = np.arange(0.0, 40.0 / 6.0, 0.2)
    s = 6.0 * t
    z = 0.01 * s + rng.normal(0, 0.075, len(t))
    g = _pessimistic_hdop_fixes(t, s, z)
    tf = np.arange(0.0, t[-1], 0.1)
    gr = road_grade(tf, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    err = np.degrees(gr.grade_rad) - math.degrees(math.atan(0.01))
    ends = (6.0 * tf < 10.0) | (6.0 * tf > 6.0 * tf[-1] - 10.0)
    assert np.max(np.abs(err[ends])) < 0.2


def test_metre_level_heights_leave_the_road_level() -> None:
    t, g = _fixes(0.02, 60.0, 3.0, seed=2, hz=1.0)
    gr = road_grade(t, g, window_m=10.0, vertical_factor=1.0, prior_sigma_rad=PRIOR)
    assert gr.mean_shrink() < 0.1  # a consumer receiver: the fit is noise, the prior wins
    assert np.max(np.abs(np.degrees(gr.grade_rad))) < 1.0


def test_a_short_track_or_no_heights_give_a_level_road() -> None:
    t, g = _fixes(0.02, 12.0, 0.05, seed=3)
    assert not road_grade(
        t, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR
    ).shrink.any()
    t, g = _fixes(0.02, 60.0, 0.05, seed=3)
    g.has_alt[:] = False
    gr = road_grade(t, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    assert not gr.grade_rad.any() and gr.mean_shrink() == 0.0
    assert not road_grade(
        t, None, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR
    ).shrink.any()


@pytest.mark.parametrize("pitch_deg", [0.0, 25.0, 45.0])
def test_the_tilt_axis_of_a_vehicle_on_a_grade_maps_to_world_up(pitch_deg: float) -> None:
    """A vehicle climbing a grade γ is pitched nose-up by γ; its camera (mount relative to the
    vehicle) seen in the world: the axis ``up_axes_in_cam`` gives maps to world up exactly."""
    R_vc = vehicle_from_cam_rotation(pitch_deg, 0.0, 0.0)
    gamma = math.radians(3.0)
    # vehicle frame: x right, y backward, z down; world (for a north-heading vehicle on a level
    # road): x east, y north, z up -> world_from_vehicle = diag(1, -1, -1); nose-up by γ is a
    # rotation about the vehicle's x axis (right)
    c, s = math.cos(gamma), math.sin(gamma)
    level = np.diag([1.0, -1.0, -1.0])
    nose_up = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])  # about world x: forward (y) rises
    R_wc = nose_up @ level @ R_vc
    ax = up_axes_in_cam(R_vc, np.array([gamma]))[0]
    assert R_wc @ ax == pytest.approx([0.0, 0.0, 1.0], abs=1e-12)
    # and with a level road, the mount's own up axis
    assert (level @ R_vc) @ up_axes_in_cam(R_vc, np.zeros(1))[0] == pytest.approx([0, 0, 1.0])


def test_height_outliers_do_not_tilt_the_grade() -> None:
    """Two fixes 5 m too high (multipath) inside the window: the Huber-weighted line keeps the
    grade (a plain fit read it 0.85° off)."""
    t, g = _fixes(0.01, 60.0, 0.05, seed=4)
    mid = len(t) // 2
    g.enu_m[mid + 3, 2] += 5.0
    g.enu_m[mid + 8, 2] += 5.0
    gr = road_grade(t, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    err = np.degrees(gr.grade_rad[mid - 20 : mid + 20]) - math.degrees(math.atan(0.01))
    assert np.max(np.abs(err)) < 0.2


def test_stations_interpolated_to_many_frames_match_the_frames_own_fits() -> None:
    """A drive with more frames than metres is fitted at 1 m stations and interpolated (the
    cost of a long drive is stations x fixes): the same grade as fitting each frame."""
    t, g = _fixes(0.01, 300.0, 0.05, seed=3, hz=5.0)
    few = np.linspace(t[0], t[-1], 40)  # fewer frames than stations: each frame's own fit
    many = np.linspace(t[0], t[-1], 6000)  # 20 frames a metre: stations
    a = road_grade(few, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    b = road_grade(many, g, window_m=10.0, vertical_factor=2.0, prior_sigma_rad=PRIOR)
    b_at_few = np.interp(few, many, b.grade_rad)
    assert np.max(np.abs(np.degrees(b_at_few - a.grade_rad))) < 0.02
    assert np.all(np.isfinite(b.grade_rad)) and np.all((b.shrink >= 0) & (b.shrink <= 1))


def test_the_variance_factor_is_exact_for_many_tight_residuals() -> None:
    """A 10-20 Hz RTK log or a stop: many residuals far below the stated σ. The factor is the
    Laplace mean at the posterior mode (checked against a bracketing root finder), and an exact
    (zero-scatter) log does not overflow."""
    from scipy.optimize import brentq

    for chi2, nu in ((1e-4, 300.0), (5e-5, 500.0), (2e-4, 300.0), (0.3, 40.0), (9.0, 60.0)):
        a, c = 2.0, 0.5 * nu * chi2  # STATED_DOF = 4 residuals: a = 2
        u = brentq(
            lambda u, a=a, c=c, nu=nu: c * math.exp(-u) - 0.5 * nu - a * u, -60, 60, xtol=1e-14
        )
        want = math.exp(u + 0.5 / (c * math.exp(-u) + a))
        assert variance_factor(chi2, nu) == pytest.approx(want, rel=1e-9)
    assert 0 < variance_factor(1e-12, 5000.0) < 1e-10
    assert 0 < variance_factor(1e-30, 1e7) < 1e-28


def test_a_stop_does_not_widen_the_first_window_along_the_track() -> None:
    """The first rung's mass is the track's typical one: 600 fixes piled up at a stop do not
    raise it (the mean density did, and every first window along the track widened 2-5x)."""
    sa = np.arange(0.0, 400.0, 1.0)  # 5 Hz at 5 m/s
    with_stop = np.sort(np.r_[sa, np.full(600, 200.0)])
    assert _typical_mass(with_stop, 10.0) == pytest.approx(_typical_mass(sa, 10.0), rel=0.02)
    mass = _typical_mass(with_stop, 10.0)
    assert _window_holding(with_stop - 100.0, mass, 10.0, 800.0) == pytest.approx(10.0, rel=1e-3)


def test_the_tilt_axis_is_world_up_seen_from_a_vehicle_rolled_by_the_cross_fall() -> None:
    """On a road falling φ to the right the vehicle rolls with it: world up, in the camera of
    any mount, is the axis ``up_axes_in_cam`` gives for that cross-fall (and grade)."""
    from scipy.spatial.transform import Rotation

    from roadsurf.core.geometry import world_from_cam
    from roadsurf.mapping.grade import up_axes_in_cam

    R_vc = Rotation.from_euler("xyz", [25.0, 2.0, -3.0], degrees=True).as_matrix()
    for fall in (0.03, -0.02):
        for grade in (0.0, 0.04):
            # world_from_cam's roll: the right wheels lower is a negative roll; pitch nose up
            R_wv = world_from_cam(37.0, -math.atan(fall), math.atan(grade))[:3, :3]
            want = R_vc.T @ R_wv.T @ np.array([0.0, 0.0, 1.0])
            got = up_axes_in_cam(R_vc, np.array([math.atan(grade)]), math.atan(fall))[0]
            # exact for each alone; together the Euler order differs at second order (γ φ)
            tol = 1e-9 if grade == 0.0 else 1e-4
            assert np.allclose(got, want, atol=tol), (fall, grade, got, want)
    # the test can fail: without the cross-fall the axis is 1.7° off
    level = up_axes_in_cam(R_vc, np.zeros(1))[0]
    R_wv = world_from_cam(37.0, -math.atan(0.03), 0.0)[:3, :3]
    want = R_vc.T @ R_wv.T @ np.array([0.0, 0.0, 1.0])
    assert math.degrees(math.acos(float(np.clip(level @ want, -1, 1)))) > 1.5
