"""GPS side of the bundle adjustment (issue 30): how far to trust the fixes, the GPS - camera
time offset over the whole drive (and the least standard error the fixes allow for it), and the
pose graph's placement kept at long scales."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.core.fits import RAYLEIGH_MEDIAN, fit_rigid_2d
from roadsurf.mapping.pose_gps import GpsFixes, interp_weights

if TYPE_CHECKING:
    from roadsurf.mapping.config import MappingConfig

# a band of centres spread less than this (m, RMS about their mean) gets no heading correction:
# its heading is not defined by its positions (a vehicle standing still)
MIN_SPREAD_M = 1.0


def keep_placement(cur: np.ndarray, world_pg: np.ndarray, length_m: float) -> np.ndarray:
    """The refined (N, 4, 4) world_from_cam moved onto the pose graph's placement (position and
    heading) at scales beyond ``length_m`` of path.

    The pose graph places the whole drive on all its GPS fixes at once; a window sees only the
    fixes of its own few metres, and every later window inherits the first one's heading through
    the held anchor frames. For each frame the refined centres within the Gaussian band (σ =
    length_m of path) are fitted to the pose graph's by a weighted rigid motion in the
    horizontal plane (rotation about up + shift, and a vertical shift), and that motion is
    applied to the frame (its centre and its rotation). So the bundle's shape within a few
    windows stays (drift over 5 m: weight 98 % at 25 m) and its placement noise goes; a band
    shorter than MIN_SPREAD_M (a vehicle standing still) gets the shift only.
    length_m <= 0: no change."""
    if length_m <= 0 or len(cur) < 2:
        return cur
    Cp = world_pg[:, :3, 3]
    Cb = cur[:, :3, 3]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(Cp, axis=0), axis=1))])
    out = cur.copy()
    # banded: beyond 4 σ the weights are < 3e-4 (memory stays linear in the drive)
    lo = np.searchsorted(s, s - 4 * length_m)
    hi = np.searchsorted(s, s + 4 * length_m, side="right")
    for i in range(len(s)):
        w = np.exp(-0.5 * ((s[lo[i] : hi[i]] - s[i]) / length_m) ** 2)
        w /= w.sum()
        b, p = Cb[lo[i] : hi[i]], Cp[lo[i] : hi[i]]
        cb, cp = w @ b, w @ p
        B, P = b[:, :2] - cb[:2], p[:, :2] - cp[:2]
        ang = 0.0
        if float(w @ np.sum(B**2, 1)) >= MIN_SPREAD_M**2:
            # weighted 2D Procrustes: the angle maximising sum w (R B)·P
            ang = math.atan2(
                float(w @ (B[:, 0] * P[:, 1] - B[:, 1] * P[:, 0])),
                float(w @ np.sum(B * P, 1)),
            )
        c, sn = math.cos(ang), math.sin(ang)
        Rz = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        Rx = _slope_rotation(w, (Rz @ (b - cb).T).T, p - cp)
        out[i, :3, 3] = Rx @ Rz @ (Cb[i] - cb) + cp
        out[i, :3, :3] = Rx @ Rz @ cur[i, :3, :3]
    return out


def _slope_rotation(w: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(3, 3) rotation about the horizontal axis across the travel that gives the refined
    centres ``b`` (M, 3; about their weighted mean, already turned onto the pose graph's
    heading) the pose graph's slope along the travel (``p``, M x 3, about its mean), weights
    ``w`` (M,). The pose graph places the drive on every fix's height at once; the windows see a
    few metres of heights each and hand their slope on through the anchor frames (potholes: the
    refined track 0.52° against the pose graph's 0.59° and the truth's 0.60°, every camera
    pitched down by the difference). Identity when the band is shorter than MIN_SPREAD_M."""
    d = p[:, :2]
    spread = float(w @ np.sum(d**2, 1))
    if spread < MIN_SPREAD_M**2:
        return np.eye(3)
    # the travel: the band's principal horizontal direction
    cov = (d * w[:, None]).T @ d
    fwd = np.append(np.linalg.eigh(cov)[1][:, 1], 0.0)
    u_b, u_p = b[:, :2] @ fwd[:2], d @ fwd[:2]
    sb = float(w @ (u_b * b[:, 2])) / max(float(w @ u_b**2), 1e-12)  # the refined slope
    sp = float(w @ (u_p * p[:, 2])) / max(float(w @ u_p**2), 1e-12)  # the pose graph's
    theta = math.atan(sp) - math.atan(sb)
    # about fwd x up: rotating fwd about it by θ raises it
    return Rotation.from_rotvec(theta * np.cross(fwd, [0.0, 0.0, 1.0])).as_matrix()


def fit_time_offset(
    cur: np.ndarray,
    t: np.ndarray,
    gps: GpsFixes,
    used: np.ndarray,
    gps_scale: float,
    cfg: MappingConfig,
) -> tuple[float, float]:
    """GPS - camera time offset τ (s) and its standard error: the fixes (inside the frames'
    time span) against the refined trajectory at t - τ, searched on a
    1 ms grid over ±bundle_max_time_offset_s and refined by a parabola (up to a rotation and
    shift: the loose trajectory's heading and placement are the part GPS decides). The per-window
    solves hold τ: in a 2 s window τ and an along-track shift are nearly one unknown."""
    sel = used & (gps.t_s >= t[0]) & (gps.t_s <= t[-1])
    if sel.sum() < 6:
        return 0.0, float("inf")
    tg, g = gps.t_s[sel], gps.enu_m[sel, :2]
    w = 1.0 / (gps.sigma_m[sel] * gps_scale) ** 2
    C = cur[:, :2, 3]
    taus = np.arange(-cfg.bundle_max_time_offset_s, cfg.bundle_max_time_offset_s + 5e-4, 1e-3)
    cost = np.empty(len(taus))
    for i, tau in enumerate(taus):
        tq = np.clip(tg - tau, t[0], t[-1])
        pred = np.column_stack([np.interp(tq, t, C[:, k]) for k in range(2)])
        cost[i] = _rigid_residual(pred, g, w)
    i = int(np.clip(np.argmin(cost), 1, len(taus) - 2))
    c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
    curv = (c0 - 2 * c1 + c2) / 1e-6  # d²cost/dτ² (cost = χ², so σ_τ² = 2 / curv)
    if curv <= 0:
        return float(taus[i]), float("inf")
    tau = float(taus[i] + 0.5e-3 * (c0 - c2) / (c0 - 2 * c1 + c2))
    dof = max(int(sel.sum()) * 2 - 3, 1)
    # the residuals are not independent: a GPS receiver's slow bias and the trajectory's own
    # drift run along the drive. With lag-one autocorrelation rho (AR(1)) the fixes count as
    # n (1 - rho) / (1 + rho) independent ones; without this an RTK drive at constant speed read
    # -66 ms +- 4 ms where the truth trajectory itself gives -66 +- 29 ms (no latency simulated)
    tq = np.clip(tg - taus[i], t[0], t[-1])
    pred = np.column_stack([np.interp(tq, t, C[:, k]) for k in range(2)])
    res = _rigid_residual(pred, g, w, residuals=True)
    rho = _lag1_correlation(res)
    inflate = (1.0 + rho) / max(1.0 - rho, 1e-3)
    se = float(np.sqrt(2.0 / curv * max(c1 / dof, 1.0) * inflate))
    return tau, se


def time_offset_bound_s(
    world: np.ndarray, t: np.ndarray, gps: GpsFixes, used: np.ndarray, gps_scale: float
) -> float:
    """Smallest standard error (s) the fixes allow for τ, whatever trajectory it is fitted to.

    With the placement free (vision gives none), a time offset is seen only through the change
    of velocity: the Fisher information is Σ w ||v_i - v̄||² (v at the fix times from the pose
    graph, w = 1/σ²). On a drive at constant speed it is ~0 and τ stays unknown, however well a
    vision-shaped trajectory's own wobble seems to pin it."""
    sel = used & (gps.t_s >= t[0]) & (gps.t_s <= t[-1])
    if sel.sum() < 3 or len(t) < 2:
        return float("inf")
    C = world[:, :2, 3]
    v_fr = np.gradient(C, t, axis=0)
    v = np.column_stack([np.interp(gps.t_s[sel], t, v_fr[:, k]) for k in range(2)])
    w = 1.0 / (gps.sigma_m[sel] * gps_scale) ** 2
    vbar = np.sum(w[:, None] * v, 0) / np.sum(w)
    info = float(np.sum(w * np.sum((v - vbar) ** 2, 1)))
    return float("inf") if info <= 0 else 1.0 / math.sqrt(info)


def _lag1_correlation(res: np.ndarray) -> float:
    """Lag-one autocorrelation (clipped to [0, 0.99]) of (G, 2) residuals in time order."""
    if len(res) < 4:
        return 0.0
    r = res - res.mean(0)
    den = float(np.sum(r**2))
    if den <= 0:
        return 0.0
    return float(np.clip(np.sum(r[1:] * r[:-1]) / den, 0.0, 0.99))


def _rigid_residual(a: np.ndarray, b: np.ndarray, w: np.ndarray, residuals: bool = False) -> Any:
    """Weighted squared residual of 2D points a against b after the best rotation + shift
    (``core.fits.fit_rigid_2d``; float), or with residuals=True the whitened (G, 2) residuals."""
    e = fit_rigid_2d(a, b, w).apply(a) - b
    if residuals:
        return np.sqrt(w)[:, None] * e
    return float(np.sum(w[:, None] * e**2))


def gps_sigma_scale(
    world: np.ndarray, t: np.ndarray, gps: GpsFixes | None, used: np.ndarray
) -> float:
    """Factor on the logged GPS σ from the pose graph's residuals (MAD; a 2D error norm has
    median ``RAYLEIGH_MEDIAN`` σ): an RTK receiver reporting HDOP states decimetres for
    centimetre fixes. Never below 1/20 (a too-good fit cannot make GPS exact)."""
    if gps is None or used.sum() < 8:
        return 1.0
    k, w = interp_weights(t, gps.t_s)
    k1 = np.minimum(k + 1, len(t) - 1)
    pred = (1 - w)[:, None] * world[k, :3, 3] + w[:, None] * world[k1, :3, 3]
    e = np.linalg.norm(pred[:, :2] - gps.enu_m[:, :2], axis=1) / gps.sigma_m
    return float(np.clip(np.median(e[used]) / RAYLEIGH_MEDIAN, 0.05, 20.0))
