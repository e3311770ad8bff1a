"""The road's grade along the drive, from the GPS heights, for the tilt prior.

The mount estimated from the pairs (``mapping.mount``) is relative to the road: the pairs'
road normals and directions of travel are both measured on it. Where the road climbs or falls,
the camera's pitch in the world is that mount plus the grade, so the pose graph's and the
bundle's tilt prior hold the mount's up axis on the road's normal, not on world up: world up
seen from the road is sin γ · forward + cos γ · up (γ > 0 uphill). A 1 % grade is 0.57°, which
at a tilted camera's 1.5 m viewing distance moves the map 15 mm along the track (tilted
drives, 25° and 45° forward: the map sat 12 mm off the truth).

The grade at each frame is the slope of a local linear fit of the fixes' heights over their
distance along the track (Gaussian weights of length ``grade_window_m``, each fix weighted by
its vertical σ), shrunk towards a level road by its standard error against the tilt prior's
σ (a grade's prior spread): γ = b · σ_g² / (σ_g² + se²). RTK heights resolve a 1 % grade to
~0.1°; a consumer receiver's metre-level heights leave γ ≈ 0, i.e. the level road the prior
assumed before, and so does a GPS track shorter than twice the window. ``shrink`` (σ_g² / (σ_g² + se²), 0-1) says how much of the fit is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from roadsurf.core.geometry import forward_in_cam, up_in_cam
from roadsurf.mapping.pose_gps import GpsFixes

MIN_FIXES = 5  # fewer fixes with a height than this: no grade (a level road)
HUBER_K = 2.0  # Huber weights beyond this many σ (the fixes' stated vertical σ)
HUBER_STEPS = 4  # reweighted fits per frame


@dataclass(frozen=True)
class RoadGrade:
    """Per frame: the grade angle γ (rad, > 0 uphill), its standard error (rad) and the share
    of the fitted slope kept (0-1)."""

    grade_rad: np.ndarray  # (n,)
    sigma_rad: np.ndarray  # (n,)
    shrink: np.ndarray  # (n,)

    @classmethod
    def level(cls, n: int) -> RoadGrade:
        z = np.zeros(n)
        return cls(z, np.full(n, np.inf), z.copy())

    def mean_shrink(self) -> float:
        return float(np.mean(self.shrink)) if len(self.shrink) else 0.0

    def to_dict(self) -> dict[str, float]:
        if not len(self.grade_rad):
            return {}
        g = np.degrees(self.grade_rad)
        return {
            "grade_mean_deg": round(float(np.mean(g)), 4),
            "grade_min_deg": round(float(np.min(g)), 4),
            "grade_max_deg": round(float(np.max(g)), 4),
            "grade_shrink_mean": round(self.mean_shrink(), 3),
        }


def road_grade(
    t: np.ndarray,
    gps: GpsFixes | None,
    *,
    window_m: float,
    vertical_factor: float,
    prior_sigma_rad: float,
) -> RoadGrade:
    """Grade at frame times ``t`` (n,) from the fixes (module docstring). ``vertical_factor``:
    the fixes' vertical σ over their horizontal σ; ``prior_sigma_rad``: the grade's prior σ."""
    n = len(t)
    if gps is None or window_m <= 0:
        return RoadGrade.level(n)
    alt = np.asarray(gps.has_alt, bool)
    if alt.sum() < MIN_FIXES:
        return RoadGrade.level(n)
    order = np.argsort(gps.t_s)
    tt, xyz, sig = gps.t_s[order], gps.enu_m[order], gps.sigma_m[order]
    alt = alt[order]
    step = np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(step)]  # distance along the GPS track (m)
    if s[-1] < 2.0 * window_m:
        # a track shorter than the window holds no local grade: its few fixes' height noise
        # over a short baseline would be the slope (40 frames, 8 m, 9 fixes of 7.5 cm: 1°)
        return RoadGrade.level(n)
    s_f = np.interp(t, tt, s)  # ... at the frames
    sa, za = s[alt], xyz[alt, 2]
    w0 = 1.0 / np.maximum(sig[alt] * vertical_factor, 1e-6) ** 2
    prior_var = math.tan(prior_sigma_rad) ** 2
    grade = np.zeros(n)
    se = np.full(n, np.inf)
    for i in range(n):
        ds = sa - s_f[i]
        k = np.exp(-0.5 * (ds / window_m) ** 2)  # kernel weight of each fix
        w = w0 * k  # ... over its vertical variance
        sw, sk = w.sum(), k.sum()
        n_eff = sk**2 / max((k**2).sum(), 1e-300)  # fixes the kernel effectively holds
        if sw <= 0 or n_eff < MIN_FIXES:
            continue
        fit = _line(ds, za, w)
        for _ in range(HUBER_STEPS):  # a height outlier (multipath) must not tilt the line
            if fit is None:
                break
            z_r = np.abs(za - fit[2] - fit[3] * (ds - fit[0])) * np.sqrt(w0)  # over its σ
            w = w0 * k * np.minimum(1.0, HUBER_K / np.maximum(z_r, 1e-12))
            fit = _line(ds, za, w)
        if fit is None:
            continue
        m, sxx, zm, b = fit
        # the stated σ, or the fixes' own scatter about the line when they disagree more
        # (reduced χ² of the kernel-weighted residuals)
        chi2 = (w * (za - zm - b * (ds - m)) ** 2).sum() / sk * n_eff / (n_eff - 2.0)
        se[i] = math.sqrt(max(chi2, 1.0) / sxx)
        grade[i] = b
    keep = prior_var / (prior_var + se**2)  # 0 where no fit (se = inf)
    return RoadGrade(np.arctan(grade * keep), np.arctan(se), keep)


def _line(x: np.ndarray, z: np.ndarray, w: np.ndarray) -> tuple[float, float, float, float] | None:
    """Weighted line z ≈ zm + b (x - m): (m, Σw (x - m)², zm, b), or None when degenerate."""
    sw = float(w.sum())
    if sw <= 0:
        return None
    m = float((w * x).sum()) / sw
    sxx = float((w * (x - m) ** 2).sum())
    if sxx <= 0:
        return None
    zm = float((w * z).sum()) / sw
    return m, sxx, zm, float((w * (x - m) * (z - zm)).sum()) / sxx


def up_axes_in_cam(R_vehicle_from_cam: np.ndarray, grade_rad: np.ndarray) -> np.ndarray:
    """(n, 3) the camera-frame axes the tilt prior holds on world up: the mount's up axis tipped
    towards its forward axis by each frame's grade (world up seen from the road is
    sin γ · forward + cos γ · up)."""
    up = up_in_cam(R_vehicle_from_cam)
    fwd = forward_in_cam(R_vehicle_from_cam)
    g = np.asarray(grade_rad, float)[:, None]
    v = np.cos(g) * up[None, :] + np.sin(g) * fwd[None, :]
    return v / np.linalg.norm(v, axis=1, keepdims=True)
