"""Plausibility of the inputs, measured against their own stated uncertainties: GPS against the
visual trajectory (camera height / scale, speed, heading, a static receiver, swapped lat/lon or a
flipped hemisphere) and the GPS σ inflation of the pose graph. Each finding is a warning with
figures (-> poses_report.json -> report.json -> HTML report); nothing is changed.

The visual trajectory is each visual component's chain of pair transforms (metric through the
camera height: α = h / d_c). Over *windows* between two GPS fixes inside a component, the GPS
chord is compared with the visual chord at the fix times. A window is long enough when the
GPS chord's relative error (√(σ_j² + σ_k²) / L, σ the stated GPS σ times the pose graph's
rescaling) is at most ``WINDOW_REL``; the visual chord's error adds the pairs' σ. Disagreements
are judged in units of these errors (``SIGMAS``); the camera height is reported beyond the 5 %
tolerance the issue states (``HEIGHT_TOL``) when the deviation is also beyond 3 σ of the
measured ratio, and a smaller scale error beyond ``SCALE_NOTE`` and 2.5 σ warns too, naming the
focal length as well (a 2 % focal error put an RTK trajectory 79 mm off). Windows whose ratios
scatter far beyond their own σ with precise GPS (``SCATTER_NOTE``) say vision's scale changes
along the drive (a lens distortion left out of camera.yaml). A GPS-file mistake (swapped
lat/lon, a flipped sign) is named only when the log as given fails the test its correction
passes: a straight drive mirrored east-west agrees with vision as well as the log itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.core.geometry import EnuReference, enu_from_lla
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.pose_gps import GpsFixes, interp_weights

if TYPE_CHECKING:
    from roadsurf.io.drive import Drive

CHECKS_VERSION = 4  # in the poses fingerprint: new checks re-run on resumed runs
WINDOW_REL = 0.05  # a window's GPS chord is known to this share (at least) of its length
SIGMAS = 5.0  # a disagreement beyond this many σ of its own error is reported
HEIGHT_TOL = 0.05  # camera height (visual scale) vs GPS: tolerance stated by the issue
# a smaller scale disagreement still warns when beyond SCALE_NOTE_SIGMAS σ: a 2 % focal error
# put an RTK trajectory 79 mm off (the pose graph trusts the pairs' scale over the fixes).
# Ordinary drives read within 0.3 %, so the 1.5 % floor keeps them quiet; 2.5 σ, not 3: the
# 2 % focal error's drive read 1.0194 +/- 0.0067 from 11 windows (2.9 σ) and went unsaid
SCALE_NOTE = 0.015
SCALE_NOTE_SIGMAS = 2.5
# windows whose GPS/visual ratios scatter this many times their own σ, with GPS this precise
# (m, median stated σ), say vision's scale changes along the drive (a lens distortion left out
# of camera.yaml: k1 -0.05 scattered them 19x), not that the GPS is noisy
SCATTER_NOTE = 5.0
SCATTER_GPS_M = 0.1


@dataclass
class Window:
    """GPS fixes j -> k (indices into GpsFixes) inside one visual component."""

    j: int
    k: int
    frame_lo: int  # frame positions spanned (for naming)
    frame_hi: int
    gps_m: np.ndarray  # (2,) GPS chord, ENU
    vis_m: np.ndarray  # (2,) visual chord, the component's chain frame
    rel_sigma: float  # relative σ of the length ratio (GPS ⊕ visual)
    dt_s: float

    @property
    def ratio(self) -> float:
        return float(np.linalg.norm(self.gps_m) / max(np.linalg.norm(self.vis_m), 1e-12))

    @property
    def bearing_diff(self) -> float:
        g, v = self.gps_m, self.vis_m
        return math.atan2(g[1], g[0]) - math.atan2(v[1], v[0])


@dataclass
class Chains:
    """Per frame position: component chain position (N, 3) and cumulative visual σ² (N,)."""

    pos: np.ndarray
    var: np.ndarray
    comp: np.ndarray


def windows(t: np.ndarray, chains: Chains, enu: np.ndarray, gps: GpsFixes, use: np.ndarray,
            sigma: np.ndarray) -> list[Window]:  # fmt: skip
    """Disjoint windows of consecutive usable fixes, each long enough for ``WINDOW_REL``."""
    out: list[Window] = []
    for c in np.unique(chains.comp):
        fr = np.flatnonzero(chains.comp == c)
        if len(fr) < 2:
            continue
        inside = np.flatnonzero(use & (gps.t_s >= t[fr[0]]) & (gps.t_s <= t[fr[-1]]))
        if len(inside) < 2:
            continue
        k_, w_ = interp_weights(t[fr], gps.t_s[inside])
        P = chains.pos[fr]
        vp = (1 - w_)[:, None] * P[k_] + w_[:, None] * P[k_ + 1]
        vv = (1 - w_) * chains.var[fr][k_] + w_ * chains.var[fr][k_ + 1]
        a = 0
        for b in range(1, len(inside)):
            j, k = inside[a], inside[b]
            g = enu[k, :2] - enu[j, :2]
            L = float(np.linalg.norm(g))
            s_g = math.hypot(sigma[j], sigma[k])
            if L <= 0 or s_g / L > WINDOW_REL:
                continue
            v = vp[b, :2] - vp[a, :2]
            Lv = max(float(np.linalg.norm(v)), 1e-12)
            rel = math.hypot(s_g / L, math.sqrt(max(vv[b] - vv[a], 0.0)) / Lv)
            lo = int(fr[k_[a]])
            hi = int(fr[min(k_[b] + 1, len(fr) - 1)])
            out.append(Window(j, k, lo, hi, g, v, rel, float(gps.t_s[k] - gps.t_s[j])))
            a = b
    return out


def ratio_scatter(ws: list[Window]) -> float:
    """The windows' GPS/visual ratios' robust scatter in units of their own σ (normalised MAD
    about the median, ``scale_estimate``'s inflation before it is applied); NaN with < 3."""
    if len(ws) < 3:
        return float("nan")
    r = np.array([w.ratio for w in ws])
    s = np.array([w.rel_sigma for w in ws]) * r
    return MAD_TO_SIGMA * float(np.median(np.abs(r - float(np.median(r))) / s))


def scale_estimate(ws: list[Window]) -> tuple[float, float] | None:
    """Robust GPS/visual length ratio and its σ: the median, then the inverse-variance mean
    of the windows within ``SIGMAS`` of it. The windows' σ are first multiplied by their own
    robust scatter (normalised MAD, when above 1: GPS noisier than it states, in place of the
    pose graph's rescaling, which a wrong camera height also drives). None without windows."""
    if not ws:
        return None
    r = np.array([w.ratio for w in ws])
    s = np.array([w.rel_sigma for w in ws]) * r
    med = float(np.median(r))
    if len(ws) >= 3:
        birge = max(1.0, ratio_scatter(ws))
        s = s * birge
        for w in ws:
            w.rel_sigma *= birge
    keep = np.abs(r - med) <= SIGMAS * s
    if not keep.any():
        keep[:] = True
    wt = 1.0 / s[keep] ** 2
    return float(np.sum(wt * r[keep]) / np.sum(wt)), float(1.0 / math.sqrt(np.sum(wt)))


def _inconsistent(ws: list[Window], ratio: float, rot_sigma_rad: float) -> list[tuple[Window, str]]:
    """Windows whose speed ratio or heading disagrees with the rest beyond ``SIGMAS``."""
    bad: list[tuple[Window, str]] = []
    for w in ws:
        if abs(w.ratio / ratio - 1) > max(SIGMAS * w.rel_sigma, HEIGHT_TOL):
            bad.append((w, "speed"))
    for w0, w1 in zip(ws[:-1], ws[1:], strict=True):
        if w1.j != w0.k:  # not adjacent (another component, or fixes skipped)
            continue
        dd = abs(math.remainder(w1.bearing_diff - w0.bearing_diff, 2 * math.pi))
        drift = rot_sigma_rad * math.sqrt(max(w1.frame_hi - w0.frame_lo, 1))
        tol = SIGMAS * math.sqrt(w0.rel_sigma**2 + w1.rel_sigma**2 + drift**2)
        if dd > tol:
            bad.append((w1, f"heading ({math.degrees(dd):.0f} deg turn GPS vs vision)"))
    return bad


def make_chains(cfg: MappingConfig, comp: np.ndarray, steps: dict[tuple[int, int], np.ndarray],
                chain: Callable[[np.ndarray], np.ndarray]) -> Chains:  # fmt: skip
    """Chain positions of every visual component (``chain(frames) -> (M, 4, 4)``) and the
    cumulative variance of the chained length from each pair's translation σ (``steps``:
    (a, b) -> cam_b_from_cam_a translation)."""
    n = len(comp)
    pos = np.zeros((n, 3))
    var = np.zeros(n)
    for c in np.unique(comp):
        fr = np.flatnonzero(comp == c)
        pos[fr] = chain(fr)[:, :3, 3]
        for i in range(1, len(fr)):
            L = float(np.linalg.norm(steps[(fr[i - 1], fr[i])]))
            s = cfg.visual_sigma_trans_m + cfg.visual_sigma_trans_rel * L
            var[fr[i]] = var[fr[i - 1]] + s * s
    return Chains(pos, var, comp)


def frame_span(names: list[str], lo: int, hi: int) -> str:
    """Frames lo..hi by name, for a warning."""
    return f"frames {names[lo]}-{names[hi]}" if hi > lo else f"frame {names[lo]}"


def check(
    cfg: MappingConfig,
    drive: Drive,
    t: np.ndarray,
    chains: Chains,
    gps: GpsFixes | None,
    ref: EnuReference | None,
    used: np.ndarray,
    gps_scale: float,
    errors_m: Callable[[], np.ndarray],
) -> tuple[list[str], dict[str, Any]]:
    """Warnings (with figures) and the measured figures of every check."""
    warn: list[str] = []
    fig: dict[str, Any] = {"version": CHECKS_VERSION}
    names = [str(f.index) for f in drive.frames]
    if gps is None or ref is None or len(gps.t_s) < 2:
        return warn, fig
    stated = gps.sigma_m
    sigma = stated * gps_scale
    if gps_scale > 1.0:
        e = errors_m()
        warn.append(
            f"GPS disagrees with the fused trajectory {gps_scale:.1f}x more than its stated "
            f"accuracy (median distance {float(np.median(e[used])):.2f} m vs stated sigma "
            f"{float(np.median(stated)):.2f} m): the pose graph inflated the GPS sigma "
            f"{gps_scale:.1f}x. Either the GPS is worse than its HDOP / mapping.gps_sigma_* "
            "say, or another input is wrong (see the other warnings)"
        )
    fig["gps_sigma_inflation"] = round(float(gps_scale), 3)
    if (~used).any():
        e = errors_m()
        bad = np.flatnonzero(~used)
        k = np.clip(np.searchsorted(t, gps.t_s[bad]), 0, len(t) - 1)
        ratio = float(np.max(e[bad] / sigma[bad]))
        why = (
            f"{ratio:.0f} sigma"
            if ratio >= cfg.gps_outlier_sigmas
            # a run of fixes that moved together where the frames' own motion did not
            # (mapping.gps_consensus), within the log's stated σ
            else f"{ratio:.0f} sigma of the stated accuracy, a step the frames' motion does "
            "not show: multipath or a wrong RTK fix"
        )
        warn.append(
            f"{len(bad)} of {len(used)} GPS fixes disagree with the visual trajectory by up to "
            f"{float(np.max(e[bad])):.2f} m ({why}) near "
            f"{frame_span(names, int(k.min()), int(k.max()))}; rejected as outliers"
        )
    rot = math.radians(cfg.visual_sigma_rot_deg)
    rsig = receiver_sigma(gps.t_s, gps.enu_m, stated)
    ws = windows(t, chains, gps.enu_m, gps, used, rsig)
    scatter = ratio_scatter(ws)
    est = scale_estimate(ws)
    fig["windows"] = len(ws)
    static = _static(t, chains, gps, rsig, names)
    ratio, ratio_s = est if est is not None else (float("nan"), float("nan"))
    bad = _inconsistent(ws, ratio, rot) if est is not None else []
    off = abs(ratio - 1.0) > HEIGHT_TOL and abs(ratio - 1.0) > 3 * ratio_s
    if off or len(bad) > len(ws) // 2 or gps_scale > 1.0 or (~used).any():
        # GPS disagrees with vision: does a typical GPS-file mistake explain it? (judged at
        # the stated σ: the inflated σ is the symptom)
        hyp = _hypotheses(drive, gps, t, chains, stated, rot)
        if hyp is not None:
            what, fix, r_h = hyp
            warn.append(
                f"{what} in {getattr(drive.gps, 'source', 'the GPS log')}: as given, GPS "
                f"disagrees with the visual trajectory (GPS sigma inflated {gps_scale:.1f}x, "
                f"{int((~used).sum())} fixes rejected); {fix}, GPS and vision agree (length "
                f"ratio {r_h:.3f}). Fix the GPS file"
            )
            fig["gps_hypothesis"] = what
            return warn, fig
    if static:  # (a swapped or flipped file also looks static: that hypothesis came first)
        warn.append(static)
    if est is None:
        fig["height"] = "not checked: GPS not precise enough over the distances driven"
        return warn, fig
    fig["gps_over_visual"] = {"ratio": round(ratio, 4), "sigma": round(ratio_s, 4)}
    h = float(drive.camera.height_m)
    lo = min((w.frame_lo for w in ws), default=0)
    hi = max((w.frame_hi for w in ws), default=0)
    others = _scale_causes(drive)
    if off:
        warn.append(
            f"camera.yaml height_m {h:.2f} m disagrees with the GPS baseline over "
            f"{frame_span(names, lo, hi)}: GPS distances are {ratio:.3f}x the visual ones "
            f"(+/- {ratio_s:.3f}, {len(ws)} window(s)); the data imply {h * ratio:.2f} m "
            f"+/- {h * ratio_s:.2f} m ({ratio - 1:+.0%}); fix height_m, unless {others}"
        )
        fig["height_implied_m"] = round(h * ratio, 4)
    elif abs(ratio - 1.0) > SCALE_NOTE and abs(ratio - 1.0) > SCALE_NOTE_SIGMAS * ratio_s:
        warn.append(
            f"GPS distances are {ratio:.3f}x the visual ones over {frame_span(names, lo, hi)} "
            f"(+/- {ratio_s:.3f}, {len(ws)} window(s)): within the {HEIGHT_TOL:.0%} the camera "
            f"height check allows, but {abs(ratio - 1) / ratio_s:.0f} sigma off, and the "
            f"trajectory follows vision's scale. camera.yaml's height_m may be "
            f"{abs(1 / ratio - 1):.1%} too {'large' if ratio < 1 else 'small'} (the data imply "
            f"{h * ratio:.3f} m for {h:.3f} m), or its focal length (fx, fy) "
            f"{abs(ratio - 1):.1%} too {'short' if ratio < 1 else 'long'} (mapping: "
            f"bundle_refine_focal: true estimates it), or {others}"
        )
        fig["height_implied_m"] = round(h * ratio, 4)
    if (
        np.isfinite(scatter)
        and scatter > SCATTER_NOTE
        and float(np.median(rsig)) <= SCATTER_GPS_M
        and gps_scale <= 1.0
    ):
        warn.append(
            f"GPS/visual length ratios scatter {scatter:.0f}x their own sigma between the "
            f"{len(ws)} GPS windows over {frame_span(names, lo, hi)}, with GPS of "
            f"{float(np.median(rsig)):.2f} m sigma: either vision's scale changes along the "
            f"drive ({others}) or the GPS clock is off the frames' (a late "
            "clock with a changing speed; see the bundle's time_offset in poses_report.json)"
        )
    fig["ratio_scatter"] = None if not np.isfinite(scatter) else round(scatter, 2)
    for w, what in bad:
        v_g = np.linalg.norm(w.gps_m) / max(w.dt_s, 1e-9)
        v_v = np.linalg.norm(w.vis_m) * ratio / max(w.dt_s, 1e-9)
        warn.append(
            f"GPS disagrees with vision in {what} over {frame_span(names, w.frame_lo, w.frame_hi)}:"
            f" GPS {v_g:.2f} m/s vs visual {v_v:.2f} m/s ({v_g / max(v_v, 1e-9) - 1:+.0%}), "
            f"window sigma {w.rel_sigma:.1%}"
        )
    return warn, fig


def _scale_causes(drive: Drive) -> str:
    """The camera.yaml omissions that change vision's scale, for a warning's text."""
    cam = drive.camera
    out = []
    if not any(float(k) != 0.0 for k in cam.dist):
        out.append("camera.yaml has no lens distortion (dist) for a lens that has some")
    if float(cam.readout_s) <= 0.0:
        out.append("no readout_s for a rolling-shutter camera")
    if not out:
        return "camera.yaml's dist or readout_s is wrong"
    return " or ".join(out)


def _hypotheses(drive: Drive, gps: GpsFixes, t: np.ndarray, chains: Chains, sigma: np.ndarray,
                rot: float) -> tuple[str, str, float] | None:  # fmt: skip
    """The GPS mistake that makes GPS agree with vision (length ratio within the height
    tolerance, no inconsistent window): swapped lat/lon, or a flipped hemisphere; None when
    none does. Returns (what, how it was corrected, the corrected length ratio)."""
    used = np.ones(len(gps.t_s), bool)
    g = drive.gps
    idx = gps.orig_index
    lat, lon = np.asarray(g.lat_deg, float)[idx], np.asarray(g.lon_deg, float)[idx]
    alt = np.zeros(len(idx))
    for name, fix, la, lo in (
        ("", "", lat, lon),  # as given: a log that passes needs no correcting
        ("lat/lon look swapped", "with the columns swapped", lon, lat),
        ("the longitude sign looks flipped (east/west)", "with the sign flipped", lat, -lon),
        ("the latitude sign looks flipped (north/south)", "with the sign flipped", -lat, lon),
    ):
        if np.any(np.abs(la) > 90):
            continue
        r = EnuReference(float(la[0]), float(lo[0]), 0.0)
        enu = enu_from_lla(la, lo, alt, r)
        ws = windows(t, chains, enu, gps, used, receiver_sigma(gps.t_s, enu, sigma))
        est = scale_estimate(ws)
        if est is None:
            continue
        ratio, ratio_s = est
        if abs(ratio - 1) <= max(HEIGHT_TOL, 3 * ratio_s) and not _inconsistent(ws, ratio, rot):
            # a straight drive mirrored east-west passes as well as the log itself: only a
            # mistake that makes a failing log pass is one
            return (name, fix, ratio) if name else None
    return None


def receiver_sigma(t_s: np.ndarray, enu_m: np.ndarray, stated: np.ndarray) -> np.ndarray:
    """(G,) horizontal σ of the fixes for the plausibility windows: the stated σ, lowered to
    the track's own fix-to-fix scatter when that is smaller (an RTK receiver logging a
    consumer-grade HDOP). The scatter is the robust σ of each fix's distance from the line
    through its two neighbours (white noise: var = σ² (1 + w₁² + w₂²)); vehicle acceleration
    only raises it, so the lowered σ stays conservative. Slowly varying GPS errors cancel in
    the short chords compared, and more than 2 windows are rescaled by their own scatter."""
    if len(t_s) < 5:
        return stated
    t0, t1, t2 = t_s[:-2], t_s[1:-1], t_s[2:]
    span = np.maximum(t2 - t0, 1e-9)
    w1, w2 = (t2 - t1) / span, (t1 - t0) / span
    pred = w1[:, None] * enu_m[:-2, :2] + w2[:, None] * enu_m[2:, :2]
    r = (enu_m[1:-1, :2] - pred) / np.sqrt(1 + w1**2 + w2**2)[:, None]
    emp = MAD_TO_SIGMA * float(np.median(np.abs(r)))
    return np.minimum(stated, max(emp, 1e-3))


def _static(t: np.ndarray, chains: Chains, gps: GpsFixes, stated: np.ndarray,
            names: list[str]) -> str | None:  # fmt: skip
    """Runs of ≥ 3 fixes within 3 stated σ of their first while vision travels beyond that
    radius by more than ``SIGMAS`` σ (a frozen or static receiver)."""
    worst = None
    # only the fixes over the frames: those outside carry the extrapolation's σ, not the
    # receiver's, and vision says nothing there
    inside = np.flatnonzero((gps.t_s >= t[0]) & (gps.t_s <= t[-1]))
    if len(inside) < 3:
        return None
    gps = gps.subset(inside)
    stated = stated[inside]
    n = len(gps.t_s)
    j = 0
    step = np.zeros(len(t))
    step[1:] = np.linalg.norm(np.diff(chains.pos, axis=0), axis=1)
    step[1:][np.diff(chains.comp) != 0] = 0.0
    travel = np.cumsum(step)
    while j < n - 2:
        k = j
        while k + 1 < n and np.linalg.norm(gps.enu_m[k + 1, :2] - gps.enu_m[j, :2]) <= 3 * max(
            stated[j], stated[k + 1]
        ):
            k += 1
        if k - j >= 2:
            lo_t, hi_t = max(gps.t_s[j], t[0]), min(gps.t_s[k], t[-1])
            if hi_t > lo_t:
                vis = float(np.interp(hi_t, t, travel) - np.interp(lo_t, t, travel))
                radius = 3 * float(np.max(stated[j : k + 1]))
                if vis - radius > SIGMAS * float(np.max(stated[j : k + 1])):
                    lo = int(np.clip(np.searchsorted(t, lo_t), 0, len(t) - 1))
                    hi = int(np.clip(np.searchsorted(t, hi_t) - 1, lo, len(t) - 1))
                    if worst is None or vis > worst[0]:
                        worst = (vis, radius, k - j + 1, lo, hi)
        j = max(k, j + 1)
    if worst is None:
        return None
    vis, radius, m, lo, hi = worst
    return (
        f"GPS looks static over {frame_span(names, lo, hi)}: {m} fixes stay within {radius:.2f} m "
        f"while vision travels {vis:.1f} m; check the receiver (frozen or no fix)"
    )
