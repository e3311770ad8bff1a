"""GPS fixes off the visual chain's local consensus (``mapping.gps_consensus``): a multipath
step is left out of the first solve, ordinary noise and the chain's drift are not."""

from __future__ import annotations

import numpy as np

from roadsurf.mapping.gps_consensus import consensus_keep
from roadsurf.mapping.pose_gps import GpsFixes


def _drive(
    n_frames: int, seconds: float, rate_hz: float, noise_m: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, GpsFixes, np.ndarray]:
    """Frame times, the chain (its own frame: rotated, 2 % short), the fixes of the true path
    (E + noise) with an HDOP-based σ of 0.4 m, and the true path at the fix times."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, seconds, n_frames)
    speed = 6.0
    s = speed * t
    true = np.c_[s, 2.0 * np.sin(s / 40.0)]  # a gentle curve (m)
    ang = 0.7
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    chain_xy = 0.98 * true @ R.T + np.array([5.0, -3.0])
    tg = np.arange(0.1, seconds - 0.1, 1.0 / rate_hz)
    g_true = np.c_[np.interp(tg, t, true[:, 0]), np.interp(tg, t, true[:, 1])]
    enu = np.c_[g_true + rng.normal(0.0, noise_m, g_true.shape), np.zeros(len(tg))]
    fixes = GpsFixes(tg, enu, np.full(len(tg), 0.4), np.ones(len(tg), bool), np.arange(len(tg)))
    return t, chain_xy, fixes, g_true


def _keep(t: np.ndarray, chain_xy: np.ndarray, g: GpsFixes) -> np.ndarray:
    return consensus_keep(t, np.zeros(len(t), int), [chain_xy], g, 1.5, 0.5)


def test_a_multipath_step_is_left_out_and_nothing_else() -> None:
    t, chain_xy, g, _ = _drive(36, 2.33, 10.0, 0.02)
    step = (g.t_s > 0.9) & (g.t_s < 1.4)  # 5 fixes 1.5 m north (5 σ of 0.4 m would pass it)
    g.enu_m[step, 1] += 1.5
    keep = _keep(t, chain_xy, g)
    assert np.array_equal(keep, ~step)
    g.enu_m[step, 1] -= 1.5
    assert _keep(t, chain_xy, g).all()


def test_noise_and_drift_are_not_steps() -> None:
    # consumer GPS: 1 m of noise, no fix left out
    t, chain_xy, g, _ = _drive(300, 60.0, 1.0, 1.0, seed=3)
    assert _keep(t, chain_xy, g).all()
    # a long RTK drive whose chain drifts 0.3 % in scale and 0.2° in heading over 600 m
    t, chain_xy, g, _ = _drive(1000, 100.0, 5.0, 0.02, seed=4)
    u = np.linspace(0.0, 1.0, len(t))[:, None]
    drift = chain_xy - chain_xy[0]
    a = np.radians(0.2) * u
    rot = np.c_[
        drift[:, 0] * np.cos(a[:, 0]) - drift[:, 1] * np.sin(a[:, 0]),
        drift[:, 0] * np.sin(a[:, 0]) + drift[:, 1] * np.cos(a[:, 0]),
    ]
    chain_d = chain_xy[0] + rot * (1.0 + 0.003 * u)
    assert _keep(t, chain_d, g).all()
    # ... where a 2 s step 1 m east is still found
    step = (g.t_s > 50.0) & (g.t_s < 52.0)
    g.enu_m[step, 0] += 1.0
    assert np.array_equal(_keep(t, chain_d, g), ~step)


def test_a_window_without_a_clear_majority_decides_nothing() -> None:
    t, chain_xy, g, _ = _drive(36, 2.33, 10.0, 0.02)
    half = g.t_s > 1.1  # half the log 1.5 m off: no majority, left to the pose graph
    g.enu_m[half, 1] += 1.5
    assert _keep(t, chain_xy, g).all()


def test_an_altitude_jump_the_frames_do_not_show_is_left_out() -> None:
    from roadsurf.mapping.gps_consensus import altitude_keep

    t, chain_xy, g, _ = _drive(60, 8.0, 5.0, 0.02, seed=5)
    rng = np.random.default_rng(5)
    # the chain climbs a 1 % grade in its own frame; the fixes 2 % (the first frame's pitch)
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(chain_xy, axis=0), axis=1))]
    chain_xyz = np.c_[chain_xy, 0.01 * along]
    fix_along = np.interp(g.t_s, t, along)
    g.enu_m[:, 2] = 95.0 + 0.02 * fix_along + rng.normal(0.0, 0.03, len(g.t_s))
    comp = np.zeros(len(t), int)
    assert altitude_keep(t, comp, [chain_xyz], g, 1.5).all()
    jump = (g.t_s > 3.0) & (g.t_s < 4.5)  # 1.5 s of fixes 2 m up
    g.enu_m[jump, 2] += 2.0
    assert np.array_equal(altitude_keep(t, comp, [chain_xyz], g, 1.5), ~jump)
    g.has_alt[:] = False  # no altitudes: nothing to judge
    assert altitude_keep(t, comp, [chain_xyz], g, 1.5).all()


def test_a_smooth_disagreement_is_not_a_step(monkeypatch) -> None:
    """A residual that grows fix by fix (a clock offset on a turn, a lever arm corrected with a
    poor heading) is the pose graph's to weigh: nothing held, though it reaches metres."""
    import roadsurf.mapping.gps_consensus as gc

    t, chain_xy, g, _ = _drive(36, 2.33, 20.0, 0.02)
    u = (g.t_s - g.t_s[0]) / np.ptp(g.t_s)
    g.enu_m[:, 1] += 2.0 * (2.0 * u - 1.0) ** 2  # a bow of 2 m, at most 19 cm per fix
    assert _keep(t, chain_xy, g).all()
    # the test can fail: judged by distance alone, the bow's end is held
    monkeypatch.setattr(gc, "_abrupt", lambda r, thr: np.abs(r) > thr)
    assert not _keep(t, chain_xy, g).all()
