"""Dense depth of a crack piece in one pair, from the parallax across the crack.

A crack is too thin for the sparse features to sample: its centre line and a road band on both
sides are tracked into image b with Lucas-Kanade, and a point below the road plane moves across
the crack by an amount proportional to its depth (``dense_crack_depth``). See ``cracks``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.fits import robust_sigma, trimmed_lstsq
from roadsurf.detection.config import CrackConfig
from roadsurf.detection.densepair import as_u8
from roadsurf.reconstruction.features import track_forward_backward
from roadsurf.reconstruction.types import PairResult


@dataclass(frozen=True)
class PairView:
    """What the dense crack-depth measurement needs of a pair besides image a: image b (raw
    pixels, like image a) and the pair's metric geometry. ``H`` (a -> b, ideal pixels) is
    only the tracking's initial guess; depths come from R, t, K and the local road plane."""

    gray_b: np.ndarray  # (H, W) image b, same camera as image a
    camera: Camera  # intrinsics and distortion of both images
    R_b_from_a: np.ndarray  # (3, 3) X_b = R X_a + t
    t_b_from_a_m: np.ndarray  # (3,) metric translation (m)

    @staticmethod
    def of(pair: PairResult, gray_b: np.ndarray, camera: Camera) -> PairView | None:
        """The view of an ok pair; None without a metric baseline (t = 0 or not finite)."""
        R = np.asarray(pair.R_b_from_a, float)
        t = np.asarray(pair.t_b_from_a_m, float)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))) or np.linalg.norm(t) <= 0:
            return None
        return PairView(gray_b, camera, R, t)


@dataclass
class DenseCrack:
    """Dense depth of one crack piece in one pair, from the parallax across the crack."""

    depth_m: np.ndarray  # (M,) depth below the local road of each valid centre-line track (m)
    # σ of one track's depth: robust spread of the side band about its fit, or the centre
    # tracks' own spread where larger (m)
    noise_m: float
    n_eff: float  # independent samples along the line: valid tracks / LK window length
    ref_var_m2: float  # variance of the local road reference (side-band fit) at the line (m²)

    def summary(self) -> tuple[float, float, float, float]:
        """(Σ depth, samples, samples below the road, variance of Σ) for the pooled test."""
        below = self.n_eff * float((self.depth_m > 0).mean())
        return self.sum_m, self.n_eff, below, self.var_m2

    @property
    def sum_m(self) -> float:
        """Σ depth over the independent samples (n_eff · mean), for the pooled test (m)."""
        return float(self.n_eff * self.depth_m.mean())

    @property
    def var_m2(self) -> float:
        """Variance of ``sum_m``: n_eff σ² (samples) + n_eff² σ_ref² (shared reference)."""
        return float(self.n_eff * self.noise_m**2 + self.n_eff**2 * self.ref_var_m2)


def ray_points(px: np.ndarray, K: np.ndarray, plane: np.ndarray, depth_m: float) -> np.ndarray:
    """(N, 3) camera-a points on the rays of ideal pixels ``px`` at ``depth_m`` below the road
    plane Z = p0 X + p1 Y + p2 (positive: farther from the camera)."""
    v = np.c_[(px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(px))]
    a, b, c = plane
    s = (c + depth_m * math.sqrt(a * a + b * b + 1.0)) / (v[:, 2] - a * v[:, 0] - b * v[:, 1])
    return v * s[:, None]


def project_px(X: np.ndarray, view: PairView) -> np.ndarray:
    Xb = X @ view.R_b_from_a.T + view.t_b_from_a_m
    q = Xb @ view.camera.K.T
    return q[:, :2] / q[:, 2:3]


def tangents(xy: np.ndarray, radius_px: float) -> np.ndarray:
    """(N, 2) unit tangent of a centre line at each of its pixels: principal direction of the
    line's pixels within ``radius_px``."""
    from scipy.spatial import cKDTree

    tree = cKDTree(xy)
    out = np.zeros_like(xy, dtype=float)
    for i, nb in enumerate(tree.query_ball_point(xy, radius_px)):
        p = xy[nb] - xy[nb].mean(axis=0)
        w, V = np.linalg.eigh(p.T @ p)
        out[i] = V[:, 1]
    return out


def dense_crack_depth(
    line: np.ndarray,
    width_px: float,
    gray_a: np.ndarray,
    view: PairView,
    plane: np.ndarray,
    cfg: CrackConfig,
) -> DenseCrack | None:
    """Dense depth of one crack piece (centre line ``line``, (H, W) bool, in image a).

    The centre-line pixels and a road band on both sides (from ``width_px`` + half the LK window
    to one window farther, so the side windows hold no crack) are tracked into image b with a
    small-window Lucas-Kanade from their road-plane prediction (forward-backward checked). A
    point ``δ`` below the road plane ``plane`` (camera a, Z = p0 X + p1 Y + p2) moves in b by
    J δ from its road prediction (J from R, t, K); only the residual's component across the
    crack is used (LK cannot see a shift along a line): δ = c·r / c·J, c the crack normal in b.
    Where the parallax runs nearly along the crack (|c·J| < ``dense_min_across`` |J|) there is
    no depth to read and None is returned. The side band's δ, fitted by a plane in the image
    (robust), is the local road; the centre's depth is its δ minus that fit and one track's
    noise is the side band's robust spread about the fit (same pair, same direction, same
    window). None when too few tracks survive.
    """
    cam = view.camera
    K = cam.K
    win = int(cfg.dense_window_px) | 1
    half = win // 2
    r0 = width_px + half + 1.0  # side band: its LK windows stay off the crack's dark band
    r1 = r0 + win
    ys, xs = np.nonzero(line)
    if len(xs) < 2 * win:
        return None
    h, w = line.shape
    m = int(math.ceil(r1)) + 2
    y0, y1 = max(0, ys.min() - m), min(h, ys.max() + m + 1)
    x0, x1 = max(0, xs.min() - m), min(w, xs.max() + m + 1)
    sub = ~line[y0:y1, x0:x1]
    dist, lab = cv2.distanceTransformWithLabels(
        sub.astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    # Label of each centre pixel (zero pixels get labels in scan order) -> its index in xs, ys.
    lab_of = np.zeros(int(lab.max()) + 1, int)
    lab_of[lab[ys - y0, xs - x0]] = np.arange(len(xs))
    sv, su = np.nonzero((dist >= r0) & (dist <= r1))
    keep = (su % 2 == 0) & (sv % 2 == 0)  # every second pixel: windows overlap anyway
    sv, su = sv[keep], su[keep]
    near = lab_of[lab[sv, su]]  # nearest centre pixel of each side pixel
    raw = np.r_[np.c_[xs, ys], np.c_[su + x0, sv + y0]].astype(float)
    n_c = len(xs)
    owner = np.r_[np.arange(n_c), near]
    # Geometry at each pixel: road prediction in b, its parallax per metre of depth, the
    # crack's normal in b.
    pa = cam.undistort_px(raw)
    X0 = ray_points(pa, K, plane, 0.0)
    if not np.all(X0[:, 2] > 0):
        return None
    pb0 = project_px(X0, view)
    J = (project_px(ray_points(pa, K, plane, 1e-3), view) - pb0) / 1e-3  # px per m of depth
    tan_a = tangents(pa[:n_c], float(win))
    ends = [project_px(ray_points(pa[:n_c] + s * tan_a, K, plane, 0.0), view) for s in (-1, 1)]
    tan_b = ends[1] - ends[0]
    tan_b /= np.maximum(np.linalg.norm(tan_b, axis=1, keepdims=True), 1e-12)
    nrm = np.c_[-tan_b[:, 1], tan_b[:, 0]][owner]
    cj = np.sum(nrm * J, axis=1)
    # LK's aperture: along the line the shift is unknown, so only the parallax across the
    # crack carries depth; nearly parallel to the parallax there is none (report, no guess).
    if np.median(np.abs(cj[:n_c])) < cfg.dense_min_across * np.median(np.linalg.norm(J, axis=1)):
        return None
    ga, gb = as_u8(gray_a), as_u8(view.gray_b)
    ra = raw.astype(np.float32).reshape(-1, 1, 2)
    rb0 = cam.distort_px(pb0).astype(np.float32).reshape(-1, 1, 2)
    rb, ra2, ok = track_forward_backward(ga, gb, ra, rb0, win, max_level=2, iterations=30)
    ok &= (
        (raw[:, 0] >= half) & (raw[:, 0] < w - half) & (raw[:, 1] >= half) & (raw[:, 1] < h - half)
    )
    if cam.mask is not None:  # windows off the camera's mask in a and in b
        ok &= cam.usable_px(raw, half + 1) & cam.usable_px(rb.reshape(-1, 2), half + 1)
    rbv = rb.reshape(-1, 2)
    hb, wb = gb.shape[:2]
    ok &= (rbv[:, 0] >= half) & (rbv[:, 0] < wb - half) & (rbv[:, 1] >= half)
    ok &= rbv[:, 1] < hb - half
    if ok[:n_c].sum() < win or ok[n_c:].sum() < 2 * win:
        return None
    # Forward-backward error against its own robust spread (as in detection/densepair.py).
    fb = np.linalg.norm((ra2 - ra).reshape(-1, 2), axis=1)
    ok &= fb <= np.median(fb[ok]) + 3.0 * max(robust_sigma(fb[ok]), 0.02)
    pb = cam.undistort_px(rbv.astype(float))
    d = np.sum(nrm * (pb - pb0), axis=1) / np.where(np.abs(cj) > 1e-9, cj, np.nan)
    # A crack floor deeper than this is a failed track (slid, or a shadow moving with the car).
    ok &= np.isfinite(d) & (np.abs(d) <= cfg.dense_max_depth_m)
    ok &= np.abs(cj) >= cfg.dense_min_across * np.linalg.norm(J, axis=1)
    c_ok, s_ok = ok[:n_c], ok[n_c:]
    if c_ok.sum() < win or s_ok.sum() < 2 * win:
        return None
    # Local road: a plane in the image through the side band's δ (robust: 3 σ trimmed).
    A = np.c_[np.ones(len(raw)), (raw - raw[:n_c].mean(axis=0)) / max(w, h)]
    fit = trimmed_lstsq(A[n_c:][s_ok], d[n_c:][s_ok], 2 * win, 1e-5)
    if fit is None:
        return None
    coef, res, _, use = fit
    # Floor: LK's sub-pixel precision (0.02 px, as the forward-backward floor in densepair.py)
    # over the parallax across the crack per metre of depth: a noiseless render is not exact.
    floor = 0.02 / max(float(np.median(np.abs(cj[:n_c][c_ok]))), 1e-9)
    sig = max(robust_sigma(res[use]), floor)
    depth = d[:n_c][c_ok] - A[:n_c][c_ok] @ coef
    # The centre's tracks may scatter more than the road's (a window on the line slides along
    # it): one track's σ is then their own spread, as for the sparse points (``cracks``).
    s_own = float(np.std(depth, ddof=1)) if len(depth) >= 3 and cfg.own_scatter else 0.0
    # Independent samples: tracks closer than one LK window share their pixels.
    n_eff = max(1.0, c_ok.sum() / win)
    n_side = max(1.0, use.sum() * 4.0 / win**2)  # side pixels every 2nd: 4 px² each
    return DenseCrack(depth, max(sig, s_own), n_eff, sig**2 / n_side)
