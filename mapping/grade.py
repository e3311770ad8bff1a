"""The road's grade along the drive, from the GPS heights, for the tilt prior.

The mount estimated from the pairs (``mapping.mount``) is relative to the road: the pairs'
road normals and directions of travel are both measured on it. Where the road climbs or falls,
the camera's pitch in the world is that mount plus the grade, so the pose graph's and the
bundle's tilt prior hold the mount's up axis on the road's normal, not on world up: world up
seen from the road is sin γ · forward + cos γ · up (γ > 0 uphill). A 1 % grade is 0.57°, which
at a tilted camera's 1.5 m viewing distance moves the map 15 mm along the track (tilted
drives, 25° and 45° forward: the map sat 12 mm off the truth).

The grade at each frame is the slope b of a local linear fit of the fixes' heights over their
distance along the track (Gaussian weights of length ``grade_window_m``, each fix weighted by
its vertical σ), shrunk towards a level road by its standard error se against the grade's own
prior σ_γ (``grade_sigma_pct``: the spread of road grades, not the tilt prior's σ, which also
holds cross-fall and vibration): γ = k · b, k = σ_γ² / (σ_γ² + se²), the posterior mean of a
grade drawn from N(0, σ_γ²) seen with error se. The se holds the fixes' white scatter (their
stated σ pooled with their scatter about the line in the log of the variance factor,
``variance_factor``) and their slow wander (a Gauss-Markov height error, ``WANDER_TAU_S``).
Grades change slowly (vertical curves run over hundreds of metres), so where a window's se is
above σ_γ / 2 the window widens, doubling up to the whole track, to where se crosses σ_γ / 2;
near a track's end (or across an outage) the first window is widened to the kernel mass it
holds mid-track (``_window_holding``). A fit that keeps less than 2/3 even there
(``MIN_SHRINK``) gives a level road. RTK heights resolve a 1 % grade to ~0.1° within 10 m; a
consumer receiver's (1 Hz, metre-level) within a few hundred metres; over a 60 m drive not at
all (se ~2.6°): there the old per-frame 10 m fits (se ~8°, shrunk against the tilt prior's 3°)
tipped frames by -1.6° to +1.9° and doubled the bundle's trajectory error (rough-gps 6.7 -> 12.1
mm). A track shorter than twice the window gives a level road. ``shrink`` (k, 0-1) says how much
of the fit is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from roadsurf.core.geometry import forward_in_cam, right_in_cam, up_in_cam
from roadsurf.mapping.pose_gps import GpsFixes

MIN_FIXES = 5  # fewer fixes with a height than this: no grade (a level road)
HUBER_K = 2.0  # Huber weights beyond this many σ (the fixes' stated vertical σ)
HUBER_STEPS = 4  # reweighted fits per frame
# widen a frame's window while its standard error exceeds this share of the grade's prior σ:
# at 0.5 the fit keeps >= 80 % of its slope (σ² / (σ² + (σ/2)²))
STATION_M = 1.0  # the grade is fitted every this far along the track (m): 1/10 of the window
MAX_STATIONS = 2000  # ... at most this many stations per drive (-): 60 km at 30 m
# bump when the estimate changes for the same fixes and settings: the poses' key holds it, so
# a resumed run does not keep poses from the earlier grade. 2: own prior, adaptive window;
# 3: fitted at stations and interpolated; 4: scale pooled in its log, first window by mass;
# 5: the factor's Newton in x from the left, the mass the track's median; 6: fitted again
# without the fixes the pose fusion rejected (mapping.poses)
GRADE_VERSION = 6
SE_OVER_PRIOR = 0.5
WINDOW_BISECTIONS = 12  # bisections in log of a first rung's 2x bracket (0.02 % of the window)
KERNEL_REACH = 5.0  # a kernel's mass counted within this many windows (the rest < 4e-6 a fix)
# the stated vertical σ (HDOP × gps_sigma_per_hdop_m × the vertical factor, a generic UERE
# scale, uncertain by a factor ~2) weighs as this many residuals against the fixes' own scatter:
# a prior on the log of the variance factor of information STATED_DOF / 2 (what that many
# residuals hold on it), i.e. a log-normal of σ 1/√2 (σ uncertain by 1.4× at 1 sd, 2× at 2 sd)
STATED_DOF = 4.0
NEWTON_STEPS = 60  # Newton steps for the log variance factor (<= 10 on real fixes, 23 at χ² 1e-30)
# the least share of the fitted slope worth keeping: the posterior mean k·b (k = σ_γ² /
# (σ_γ² + se²)) has a mean squared error σ_γ²(1 - k)(1 + 3k) when se is understated 2× (wander,
# multipath), less than a level road's σ_γ² only for k > 2/3 (se < σ_γ / √2); below, the grade
# is mostly the noise model's guess and the road is taken level
MIN_SHRINK = 2.0 / 3.0
# correlation time of a receiver's height error (s): satellite geometry, ionosphere and
# multipath change over minutes, so over a drive of seconds the error wanders like a random walk
# of q² = 2 σ² / τ (a first-order Gauss-Markov process of σ the stated vertical σ), which no
# scatter about the line shows: over 15 s at 4 m/s it alone tilts a consumer receiver's slope by
# ~0.9° (σ 1.7 m); the simulator's consumer profile wanders 1.5 m per √60 s
WANDER_TAU_S = 120.0


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
    sa, za, ta = s[alt], xyz[alt, 2], tt[alt]
    w0 = 1.0 / np.maximum(sig[alt] * vertical_factor, 1e-6) ** 2
    dt = np.r_[0.0, np.diff(ta)]  # time between successive fixes (s)
    prior_var = math.tan(prior_sigma_rad) ** 2
    # the grade is smooth along the track by design: it is fitted at stations every STATION_M
    # (at most MAX_STATIONS over the drive) and interpolated to the frames, so a long drive
    # costs stations x fixes, not frames x fixes
    span = float(s_f.max() - s_f.min())
    spacing = max(STATION_M, span / MAX_STATIONS)
    if span / spacing + 1 < n:
        at = np.linspace(float(s_f.min()), float(s_f.max()), int(math.ceil(span / spacing)) + 1)
    else:
        at = s_f
    m = len(at)
    grade = np.zeros(m)
    se = np.full(m, np.inf)
    # the windows tried, narrowest first, doubling up to the whole track (a kernel twice the
    # track's length: each fix keeps >= 88 % of its weight)
    windows = [window_m]
    while windows[-1] < 2.0 * s[-1]:
        windows.append(min(2.0 * windows[-1], 2.0 * float(s[-1])))
    target = SE_OVER_PRIOR * math.sqrt(prior_var)
    # the first rung's kernel mass at a typical place along the track (the median over evenly
    # spaced points: a stop or a slow stretch piles fixes up in a few metres and must not set it
    # for the rest of the track, as the mean density did: 2-5x wider first windows)
    mass = _typical_mass(sa, window_m)
    for i in range(m):
        prev: tuple[float, float] | None = None  # (window, se) of the last rung tried
        first = _window_holding(sa - at[i], mass, window_m, windows[-1])
        for win in [first, *(w for w in windows if w > first)]:
            got = _local_slope(sa - at[i], za, w0, dt, win)
            if got is None:
                continue
            grade[i], se[i] = got
            if se[i] <= target:
                if prev is not None and prev[1] > target:
                    # the window where se crosses the target, interpolated in log-log between
                    # the two rungs: it moves smoothly along the track, so does the grade (the
                    # rungs alone switch neighbouring frames' windows 2× apart: 0.3° steps)
                    u = math.log(prev[1] / target) / math.log(prev[1] / se[i])
                    got = _local_slope(sa - at[i], za, w0, dt, prev[0] * (win / prev[0]) ** u)
                    if got is not None:
                        grade[i], se[i] = got
                break
            prev = (win, se[i])
    keep = prior_var / (prior_var + se**2)  # 0 where no fit (se = inf)
    # a fit that keeps less than MIN_SHRINK of its slope even over the whole track: a level road
    keep[keep < MIN_SHRINK] = 0.0
    if at is not s_f:
        big = 1e6  # se beyond any grade (rad): np.interp cannot take inf
        g_f = np.interp(s_f, at, grade * keep)
        keep_f = np.interp(s_f, at, keep)
        se_f = np.interp(s_f, at, np.minimum(se, big))
        se_f[se_f >= big] = np.inf
        return RoadGrade(np.arctan(g_f), np.arctan(se_f), keep_f)
    return RoadGrade(np.arctan(grade * keep), np.arctan(se), keep)


def _typical_mass(sa: np.ndarray, win: float) -> float:
    """The median over 201 evenly spaced points of the track of the kernel mass (σ ``win``, m)
    over the fixes at distances ``sa`` (m, ascending) along it."""
    probes = np.linspace(float(sa[0]), float(sa[-1]), 201)
    return float(np.median([_kernel_mass(sa - p, win) for p in probes]))


def _kernel_mass(ds: np.ndarray, win: float) -> float:
    """Mass of a Gaussian kernel of σ ``win`` (m) over fixes at distances ``ds`` (m, ascending),
    counted within ``KERNEL_REACH`` windows."""
    a, b = np.searchsorted(ds, [-KERNEL_REACH * win, KERNEL_REACH * win])
    return float(np.exp(-0.5 * (ds[a:b] / win) ** 2).sum())


def _window_holding(ds: np.ndarray, mass: float, lo: float, hi: float) -> float:
    """The Gaussian window (m, within [lo, hi]) whose kernel over the fixes at distances ``ds``
    (m, ascending) holds ``mass``: near a track's end, or across a GPS outage, a kernel loses
    fixes on one side, and the local slope fitted from the half it keeps (its centroid a window
    inside the track) is the noisiest and, through the se, the most shrunk on the track.
    Widening the first rung there to the kernel mass it holds elsewhere (the nearest-neighbour
    bandwidth of kernel regression at a boundary) keeps the first rung's data the same along the
    track; the ladder then widens it as everywhere. The mass grows with the window: doubled to a
    bracket, then bisected in log."""

    if _kernel_mass(ds, lo) >= mass:
        return lo
    low, high = lo, min(2.0 * lo, hi)
    while _kernel_mass(ds, high) < mass:
        if high >= hi:
            return hi
        low, high = high, min(2.0 * high, hi)
    a, b = math.log(low), math.log(high)
    for _ in range(WINDOW_BISECTIONS):
        mid = 0.5 * (a + b)
        if _kernel_mass(ds, math.exp(mid)) < mass:
            a = mid
        else:
            b = mid
    return math.exp(b)


def _local_slope(
    ds: np.ndarray, za: np.ndarray, w0: np.ndarray, dt: np.ndarray, window_m: float
) -> tuple[float, float] | None:
    """Slope of the fixes' heights ``za`` over their distance ``ds`` (m) from the frame, Gaussian
    kernel of σ ``window_m`` times the fixes' weights ``w0`` (1/σ², Huber-reweighted), and its
    standard error (white scatter and slow wander, module docstring); ``dt`` (s): time since the
    previous fix. None with too few fixes in the window."""
    k = np.exp(-0.5 * (ds / window_m) ** 2)  # kernel weight of each fix
    w = w0 * k  # ... over its vertical variance
    sw, sk = w.sum(), k.sum()
    n_eff = sk**2 / max((k**2).sum(), 1e-300)  # fixes the kernel effectively holds
    if sw <= 0 or n_eff < MIN_FIXES:
        return None
    fit = _line(ds, za, w)
    for _ in range(HUBER_STEPS):  # a height outlier (multipath) must not tilt the line
        if fit is None:
            break
        z_r = np.abs(za - fit[2] - fit[3] * (ds - fit[0])) * np.sqrt(w0)  # over its σ
        w = w0 * k * np.minimum(1.0, HUBER_K / np.maximum(z_r, 1e-12))
        fit = _line(ds, za, w)
    if fit is None:
        return None
    m, sxx, zm, b = fit
    # the fixes' scale: their reduced χ² about the line (ν = n_eff - 2 residuals) pooled with
    # the stated σ (variance_factor): an RTK receiver's heights scatter ~10× less than its
    # HDOP × 0.5 m says, a consumer's scatter as stated, and a few residuals move it little
    nu = n_eff - 2.0
    chi2 = (w * (za - zm - b * (ds - m)) ** 2).sum() / sk * n_eff / nu
    factor = variance_factor(chi2, nu)
    # slow wander: a random walk of q² = 2 σ² / WANDER_TAU_S (σ² the kernel-weighted stated
    # variance, scaled like the scatter) moves the slope by q² Σ_i Δt_i (Σ_{j >= i} c_j)², c_j =
    # w_j (x_j - m) / Sxx the line's weights on the heights (they sum to 0)
    c = w * (ds - m) / sxx
    tail = np.cumsum(c[::-1])[::-1]  # Σ_{j >= i} c_j
    q2 = 2.0 * factor * float((k / w0).sum() / sk) / WANDER_TAU_S
    var_wander = q2 * float((dt * tail**2).sum())
    return b, math.sqrt(factor / sxx + var_wander)


def variance_factor(chi2: float, nu: float, prior_dof: float = STATED_DOF) -> float:
    """Posterior mean of the fixes' variance factor f (their variance over the stated one) from
    a reduced χ² ``chi2`` of ``nu`` residuals and a log-normal prior on f at 1 holding
    ``prior_dof`` residuals' information (ν₀/2 on log f).

    With u = log f, the residuals give ν χ² / f ~ χ²_ν: log-likelihood -ν u / 2 - ν χ² e^-u / 2,
    information ν / 2 on u. The posterior mode solves ν χ² e^-u / 2 = ν / 2 + ν₀ u / 2 (Newton,
    the left side falls and the right rises with u: one root); its mean under the Laplace
    approximation is exp(u + 1 / (2 I)), I = ν χ² e^-u / 2 + ν₀ / 2. A scale is pooled in its
    log: a scaled inverse-χ² prior of ν₀ residuals pools arithmetically, (ν₀ + ν χ²) / (ν₀ + ν),
    and holds f >= ν₀ / (ν₀ + ν) whatever the residuals say: an RTK receiver's 1/100 (heights
    10× better than HDOP × 0.5 m) read as 0.15 from 24 fixes (benchmarks.variation's
    mount15_r0: the white se 3.9× what the scatter gives, the 1 % grade dropped as unresolved);
    here 0.028. Where the scatter is within ~2× of the stated σ the two agree within ~10 % (ν ≥ 7;
    a few % for ν ≥ 20)."""
    if not (nu > 0 and chi2 > 0 and math.isfinite(chi2)):
        return 1.0  # no residual scatter to go by: the stated σ
    a, half = 0.5 * prior_dof, 0.5 * nu
    lc = math.log(half) + math.log(chi2)  # log c, c = ν χ² / 2
    # The mode solves c e^-u = ν/2 + a u. In x = ν/2 + a u (> 0 at the mode): φ(x) = log c +
    # ν/(2a) - x/a - log x = 0; φ falls and is convex, so Newton from a point left of the root
    # rises to it monotonically; x = min(c, ν/2) is one (φ(c) = (ν/2 - c)/a, φ(ν/2) = log χ²).
    # Newton in u from the arithmetic pool overshot far left for χ² << 1 with many residuals
    # (a 10-20 Hz RTK log, a stop) and crawled back, or overflowed exp(-u)
    x = min(math.exp(lc), half)
    for _ in range(NEWTON_STEPS):
        step = (lc + half / a - x / a - math.log(x)) / (1.0 / a + 1.0 / x)
        x += step
        if abs(step) <= 1e-13 * x:
            break
    # the information at the mode: c e^-u + a = x + a
    return math.exp((x - half) / a + 0.5 / (x + a))


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


def up_axes_in_cam(
    R_vehicle_from_cam: np.ndarray, grade_rad: np.ndarray, cross_fall_rad: float = 0.0
) -> np.ndarray:
    """(n, 3) the camera-frame axes the tilt prior holds on world up: the mount's up axis tipped
    towards its forward axis by each frame's grade γ and away from its right axis by the road's
    cross-fall φ (+ = the road falls to the right, and the vehicle rolls with it): world up seen
    from the road is sin γ · forward + cos γ (cos φ · up − sin φ · right)."""
    up = up_in_cam(R_vehicle_from_cam)
    fwd = forward_in_cam(R_vehicle_from_cam)
    right = right_in_cam(R_vehicle_from_cam)
    g = np.asarray(grade_rad, float)[:, None]
    across = math.cos(cross_fall_rad) * up - math.sin(cross_fall_rad) * right
    v = np.cos(g) * across[None, :] + np.sin(g) * fwd[None, :]
    return v / np.linalg.norm(v, axis=1, keepdims=True)
