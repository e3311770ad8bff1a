"""GPS fixes that leave the visual chain's local consensus, found before the pose graph.

A multipath or a wrong RTK fix moves a run of consecutive fixes together, metres off for a
second or two. The pose graph's robust loss and its outlier test judge each fix against a
solution those fixes already pulled: a 1.5 m step over 1 s of a 36-frame drive (5 of 26
fixes) left the trajectory 0.26 m off with no fix rejected, and the defects there misplaced
(a helper's battery, session 34). Vision sees no step: the frames' chained motion (each
visual component's ``pose_init.chain``) is smooth. So within a sliding time window every fix
is compared with the similarity (rotation, scale, shift: the chain's metric scale rests on the
camera height, a few % off) that most of the window's fixes agree on (least median of squares
over pairs of fixes). A fix further than max(``STEP_SPREADS`` × the majority's own spread,
``MIN_STEP_M``) from it, in a run of such fixes that begins or ends with a jump of that size
(``_abrupt``: a smooth disagreement such as a clock offset on a turn is no step), is held out
of the pose graph (``PoseGraph(gps_used=...)``), and rejoins only where the solution comes
within ``pose_graph.HELD_READMIT_M`` of it. The spread is measured, not the log's stated σ:
an RTK log's HDOP says 0.3-0.5 m where its fixes scatter by 2 cm, and its 5 σ let a 1.5 m
step through.

The window is short (``WINDOW_S``) so that the chain's drift inside it stays far below the
step (0.05-0.1 % of the distance: centimetres over a window at speed), and a window whose
fixes do not agree by a clear majority (``MAJORITY``) decides nothing: an episode longer than
half a window is left to the pose graph. Pure function of the chain and the fixes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from roadsurf.mapping.pose_gps import GpsFixes, interp_weights

WINDOW_S = 10.0  # a window's length (s): longer than a multipath episode, short for drift
MIN_FIXES = 6  # fewer fixes in a window: it decides nothing
MAJORITY = 0.6  # the share of a window's fixes the consensus needs, or it decides nothing
FLOOR_M = 0.01  # the smallest spread of the consensus (m): the chain's own noise
STEP_SPREADS = 6.0  # a fix this many spreads (and MIN_STEP_M) off the consensus is out
MIN_STEP_M = 0.3  # ... (m): smaller disagreements are the pose graph's to weigh
SCALE_RANGE = (0.8, 1.25)  # the chain's scale against the GPS a candidate may have (-)
MAX_CANDIDATES = 300  # pairs of fixes tried per window


def consensus_keep(
    t: np.ndarray,
    comp: np.ndarray,
    chain_xy: list[np.ndarray],
    gps: GpsFixes,
    margin_s: float,
    min_baseline_m: float,
) -> np.ndarray:
    """(G,) bool: the fixes of ``gps`` that agree with their window's consensus (True also
    for fixes no window judged). ``t`` (N,) frame times (s); ``comp`` (N,) each frame's visual
    component; ``chain_xy[c]`` (M_c, 2) the chained horizontal positions of component c's
    frames (any frame of reference, m); ``margin_s`` how far (s) outside the drive's first and
    last frame a fix still belongs to the end components; ``min_baseline_m`` the shortest
    chain distance between two fixes a candidate is fitted on (m)."""
    rng = np.random.default_rng(0)
    keep = np.ones(len(gps.t_s), bool)
    for c, idx, k, w in _component_fixes(t, comp, gps, margin_s, need_alt=False):
        xy = np.asarray(chain_xy[c], float)
        src = (1 - w)[:, None] * xy[k] + w[:, None] * xy[k + 1]
        src_c = src[:, 0] + 1j * src[:, 1]
        dst_c = gps.enu_m[idx, 0] + 1j * gps.enu_m[idx, 1]

        def similarity(win: np.ndarray, a: np.ndarray = src_c, b: np.ndarray = dst_c) -> Any:
            return _consensus_residuals(a[win], b[win], min_baseline_m, rng)

        _judge(gps.t_s[idx], idx, keep, similarity)
    return keep


def altitude_keep(
    t: np.ndarray, comp: np.ndarray, chain_xyz: list[np.ndarray], gps: GpsFixes, margin_s: float
) -> np.ndarray:
    """(G,) bool: the fixes whose altitude agrees with their window's consensus (True also for
    fixes without one or no window judged): the altitude minus the chain's height, a level
    plus a grade along the chain's path (least median of squares over pairs of fixes), out
    beyond max(``STEP_SPREADS`` × the majority's spread, ``MIN_STEP_M``). A 2 m altitude step
    mid-drive (a helper's battery) otherwise went into the grade and the map's heights, 1.1 m
    off, with no word. Arguments as ``consensus_keep``, ``chain_xyz[c]`` (M_c, 3)."""
    rng = np.random.default_rng(0)
    keep = np.ones(len(gps.t_s), bool)
    for c, idx, k, w in _component_fixes(t, comp, gps, margin_s, need_alt=True):
        xyz = np.asarray(chain_xyz[c], float)
        path = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1))]
        along = (1 - w) * path[k] + w * path[k + 1]
        y = gps.enu_m[idx, 2] - ((1 - w) * xyz[k, 2] + w * xyz[k + 1, 2])

        def line(win: np.ndarray, x: np.ndarray = along, z: np.ndarray = y) -> Any:
            return _line_residuals(x[win], z[win], rng)

        _judge(gps.t_s[idx], idx, keep, line)
    return keep


def _component_fixes(
    t: np.ndarray, comp: np.ndarray, gps: GpsFixes, margin_s: float, need_alt: bool
) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """Per visual component with at least ``MIN_FIXES`` fixes in its time span (the end
    components ``margin_s`` beyond it; with ``need_alt`` only fixes with an altitude): (c, the
    fixes' indices, the component's frame k before each fix and the weight w of frame k + 1)."""
    n = len(t)
    for c in range(int(comp.max()) + 1 if n else 0):
        fr = np.flatnonzero(comp == c)
        if len(fr) < 2:
            continue
        lo = margin_s if fr[0] == 0 else 0.0
        hi = margin_s if fr[-1] == n - 1 else 0.0
        sel = (gps.t_s >= t[fr[0]] - lo) & (gps.t_s <= t[fr[-1]] + hi)
        idx = np.flatnonzero(sel & gps.has_alt if need_alt else sel)
        if len(idx) >= MIN_FIXES:
            k, w = interp_weights(t[fr], gps.t_s[idx])
            yield c, idx, k, w


def _judge(
    ts: np.ndarray,
    idx: np.ndarray,
    keep: np.ndarray,
    residuals: Callable[[np.ndarray], tuple[np.ndarray, float] | None],
) -> None:
    """Windows of ``WINDOW_S`` every quarter window over the (sorted) fix times ``ts``; each
    judges the fixes of its middle half by ``residuals(window) -> (residuals (m; complex E +
    iN, or real), spread) | None`` and clears ``keep[idx[...]]`` of those beyond
    max(``STEP_SPREADS`` spreads, ``MIN_STEP_M``) in a run that starts or ends with a jump
    of that size (``_abrupt``)."""
    for t0 in np.arange(ts[0], ts[-1] + WINDOW_S / 4, WINDOW_S / 4):
        lo = int(np.searchsorted(ts, t0 - WINDOW_S / 2, side="left"))
        hi = int(np.searchsorted(ts, t0 + WINDOW_S / 2, side="right"))
        win = np.arange(lo, hi)
        if len(win) < MIN_FIXES:
            continue
        got = residuals(win)
        if got is None:
            continue
        r, spread = got
        out = _abrupt(r, max(STEP_SPREADS * spread, MIN_STEP_M))
        mid = np.abs(ts[win] - t0) <= WINDOW_S / 4
        keep[idx[win[out & mid]]] = False


def _abrupt(r: np.ndarray, thr: float) -> np.ndarray:
    """(m,) bool: the residuals ``r`` (m,) beyond ``thr`` whose run of such (consecutive
    fixes) begins or ends with a jump beyond ``thr`` from its neighbour. A multipath step
    appears and vanishes between two fixes; the residual of a smooth disagreement (a clock
    offset on a turn, a lever arm corrected with a poor heading) grows fix by fix and is the
    pose graph's to weigh (a 0.3 s offset on a 40 m S-curve: 10 good fixes held and the
    shape 6.9 → 39.9 mm, a review helper)."""
    far = np.abs(r) > thr
    out = np.zeros(len(r), bool)
    k = 0
    while k < len(r):
        if not far[k]:
            k += 1
            continue
        e = k
        while e + 1 < len(r) and far[e + 1]:
            e += 1
        onset = k > 0 and abs(r[k] - r[k - 1]) > thr
        end = e + 1 < len(r) and abs(r[e + 1] - r[e]) > thr
        out[k : e + 1] = onset or end
        k = e + 1
    return out


def _pairs(m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i < j) of m fixes: all of them, or ``MAX_CANDIDATES`` drawn at random."""
    ii, jj = np.triu_indices(m, 1)
    if len(ii) > MAX_CANDIDATES:
        pick = rng.choice(len(ii), MAX_CANDIDATES, replace=False)
        ii, jj = ii[pick], jj[pick]
    return ii, jj


def _majority(res: np.ndarray) -> np.ndarray | None:
    """(m,) bool: the fixes within 2.5 LMedS scales (Rousseeuw & Leroy) of the best candidate,
    whose distances are ``res`` (m,); None when they are not a clear majority (``MAJORITY``)."""
    m = len(res)
    s0 = 1.4826 * (1.0 + 5.0 / max(m - 2, 1)) * float(np.median(res))
    inl = res <= max(2.5 * s0, FLOOR_M)
    return inl if inl.sum() >= max(MAJORITY * m, 3) else None


def _line_residuals(
    x: np.ndarray, y: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, float] | None:
    """(m,) signed residuals (m) of ``y`` from the line y = p + q x most points agree on
    (least median of squares over pairs, a level where x barely varies), refitted on that
    majority, and the majority's robust spread (m); None without a clear majority."""
    m = len(x)
    ii, jj = _pairs(m, rng)
    dx = x[jj] - x[ii]
    ok = np.abs(dx) > 1e-6
    q = np.zeros(len(ii))
    q[ok] = (y[jj][ok] - y[ii][ok]) / dx[ok]
    p = y[ii] - q * x[ii]
    res = np.abs(p[:, None] + q[:, None] * x[None, :] - y[None, :])
    best = int(np.argmin(np.median(res, axis=1)))
    inl = _majority(res[best])
    if inl is None:
        return None
    A = np.c_[np.ones(int(inl.sum())), x[inl]]
    coef = np.linalg.lstsq(A, y[inl], rcond=None)[0]
    r = y - (coef[0] + coef[1] * x)
    return r, max(1.4826 * float(np.median(np.abs(r[inl]))), FLOOR_M)


def _consensus_residuals(
    src: np.ndarray, dst: np.ndarray, min_baseline_m: float, rng: np.random.Generator
) -> tuple[np.ndarray, float] | None:
    """The residuals (m; complex E + iN) of the fixes ``dst`` (complex) from the similarity of
    the chain positions ``src`` (complex) that most of them agree on, refitted on that
    majority, and the robust spread (m) of its distances: (residuals (m,), spread). Least
    median of squares over pairs of fixes, so no stated σ enters (an RTK log's HDOP-based σ
    is 0.3-0.5 m where its fixes scatter by 2 cm). None when no candidate has a clear
    majority (``MAJORITY``)."""
    m = len(src)
    ii, jj = _pairs(m, rng)
    ds = src[jj] - src[ii]
    ok = np.abs(ds) >= min_baseline_m
    ii, jj, ds = ii[ok], jj[ok], ds[ok]
    if not len(ii):
        return None
    a = (dst[jj] - dst[ii]) / ds  # rotation and scale
    ok = (np.abs(a) >= SCALE_RANGE[0]) & (np.abs(a) <= SCALE_RANGE[1])
    ii, a = ii[ok], a[ok]
    if not len(ii):
        return None
    b = dst[ii] - a * src[ii]
    res = np.abs(a[:, None] * src[None, :] + b[:, None] - dst[None, :])  # (candidates, m)
    best = int(np.argmin(np.median(res, axis=1)))
    inl = _majority(res[best])
    if inl is None:
        return None
    c_s, c_d = src[inl].mean(), dst[inl].mean()
    sc, dc = src[inl] - c_s, dst[inl] - c_d
    den = float(np.sum(np.abs(sc) ** 2))
    a_fit = np.sum(np.conj(sc) * dc) / den if den > 0 else a[best]
    r = dst - (a_fit * (src - c_s) + c_d)
    spread = max(1.4826 * float(np.median(np.abs(r[inl]))), FLOOR_M)
    return np.asarray(r), spread
