"""Depth of a crack piece in one pair from a groove model fitted to its cross-section profiles.

Why not the dark band's shift. A groove's floor moves between the views by its depth times the
change of the ray's slope, but its rims stay: the surface under a profile across the crack is
re-mapped, s -> s + Δτ D(s), with both ends fixed. A window's mean shift (Lucas-Kanade) or the
band's centroid therefore sees only a share of the depth: to first order the centroid moves by
Δτ ∫ D s k'(s) ds / ∫ k ds (k the darkness profile), 0.4 D for a band darkest at the floor and
0.15 D for the simulator's band, which fades out over 0.9 w either side, beyond the groove's
w / 2. On a busy texture (gravel) the window's own texture, at road level, dominates the
shift: the 3.4 mm deep, 5.7 mm wide D007 of the simulated potholes drive read 0.28 mm by LK
(0.50 / 0.12 mm with 5 / 9 px windows), 0.2 mm by the band's centroid: z 1.3, missed.

The groove model instead predicts image b's profile from image a's: the surface point seen at
offset s across the crack in image a (ideal pixel q_a(s)) appears in image b at its road-level
position p_0(s) (the pair's road plane, R, t, K) moved by J(s) (D g(s) + e), J the image motion
per metre below the road, g(s) = (1 - (2 (s - c) / w)²)_+ the parabolic groove (c the dark band's
centre in image a, w the crack's measured width) and e a depth offset shared by the profile (the
local road's residual parallax). Per profile, Gauss-Newton on I_b(p_0 + J (D g + e)) = α I_a + β
(gain and offset: exposure) gives D. A dark line at road level gives D = 0 whatever its darkness
profile (only its position is tested, not its shape), and the road texture moves with e, not D.
It reads 1.2 mm of D007's 3.4 mm (z 8.9 in one pair; the rendered band, blur and JPEG spread
the floor's displacement), a lower bound like every dense depth. D, e, α and β are shared by
the profiles of a block of ``groove_block_px`` along the crack (neighbouring profiles share
pixels; one profile of a crack 1-2 px wide cannot separate its four unknowns), and the
blocks' mean depth over its standard error is turned into the normal z of the same one-sided
level (Student's t, blocks - 1 degrees of freedom), which the pooled test (``crackmap``)
reads. Tests:
``tests/detection/test_crack_groove.py``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackdepth import (
    DenseCrack,
    PairView,
    project_px,
    ray_points,
    tangents,
)


def _sample(img: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at raw pixels ``px`` (..., 2); NaN outside."""
    shp = px.shape[:-1]
    flat = px.reshape(-1, 2).astype(np.float32)
    k = len(flat)
    cols = 1024  # OpenCV's maps must stay below 32767 rows and columns
    m = np.full((-(-k // cols) * cols, 2), -1e4, np.float32)
    m[:k] = flat
    m = m.reshape(-1, cols, 2)
    out = cv2.remap(
        img, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    )  # fmt: skip
    return out.reshape(-1)[:k].reshape(shp)


def groove_crack_depth(
    line: np.ndarray,
    width_px: float,
    gray_a: np.ndarray,
    view: PairView,
    plane: np.ndarray,
    cfg: CrackConfig,
) -> DenseCrack | None:
    """Depth of one crack piece (centre line ``line``, (H, W) bool, raw pixels of image a;
    ``width_px`` its measured width) from a groove model fitted to its cross-section profiles
    in both images (see the module docstring). ``plane``: the pair's road plane in camera a,
    Z = p0 X + p1 Y + p2. None when the parallax runs along the crack (within
    ``dense_min_across``) or fewer than ``groove_min_blocks`` blocks are measured."""
    cam = view.camera
    K = cam.K
    ys, xs = np.nonzero(line)
    blk = float(cfg.groove_block_px)
    if len(xs) < cfg.groove_min_blocks * blk:
        return None
    raw = np.c_[xs, ys].astype(float)
    pa = cam.undistort_px(raw)
    tan_a = tangents(pa, 3.5)
    nrm_a = np.c_[-tan_a[:, 1], tan_a[:, 0]]
    w = max(float(width_px), 1.0)
    half = max(3.0, 1.5 * w + 2.0)  # the groove, its darkened rims and some road each side
    s = np.arange(-half, half + 1e-9, 0.5)
    ga = np.asarray(gray_a, np.float32)
    gb = np.asarray(view.gray_b, np.float32)
    # The dark band's centre in image a (its darkness-weighted mean offset): the groove's axis.
    qa = pa[:, None, :] + s[None, :, None] * nrm_a[:, None, :]
    Ia = _sample(ga, cam.distort_px(qa.reshape(-1, 2)).reshape(qa.shape))
    inside = np.all(np.isfinite(Ia), axis=1)  # profiles within image a
    if not inside.any():
        return None
    Ia = np.where(inside[:, None], Ia, 0.0)
    dark = np.clip(Ia.max(axis=1, keepdims=True) - Ia, 0.0, None)
    inner = np.abs(s) <= 0.5 * w + 1.0
    c = np.nansum(dark[:, inner] * s[inner], axis=1) / np.maximum(
        np.nansum(dark[:, inner], axis=1), 1e-9
    )
    g = np.clip(1.0 - (2.0 * (s[None, :] - c[:, None]) / w) ** 2, 0.0, None)
    # Road-level positions in b and the image motion per metre below the road there.
    flat = qa.reshape(-1, 2)
    X0 = ray_points(flat, K, plane, 0.0)
    if not np.all(X0[:, 2] > 0):
        return None
    p0 = project_px(X0, view)
    J = (project_px(ray_points(flat, K, plane, 1e-3), view) - p0) / 1e-3
    p0, J = p0.reshape(qa.shape), J.reshape(qa.shape)
    # LK's aperture holds here too: only the motion across the crack is seen.
    ends = [project_px(ray_points(pa + d * tan_a, K, plane, 0.0), view) for d in (-1, 1)]
    tan_b = ends[1] - ends[0]
    tan_b /= np.maximum(np.linalg.norm(tan_b, axis=1, keepdims=True), 1e-12)
    nrm_b = np.c_[-tan_b[:, 1], tan_b[:, 0]]
    j0 = J[:, len(s) // 2]
    cj = np.abs(np.sum(nrm_b * j0, axis=1))
    if np.median(cj) < cfg.dense_min_across * np.median(np.linalg.norm(j0, axis=1)):
        return None
    gx = cv2.Sobel(gb, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(gb, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    n = len(xs)
    D = np.zeros(n)
    e = np.zeros(n)
    ok = inside.copy()
    # Blocks of ``groove_block_px`` along the crack (image cells: any curve). Each block fits
    # one depth, one road shift and one gain and offset to all its profiles together. A
    # profile spans only a few pixels across a narrow crack, and there its own four unknowns
    # are nearly collinear (the groove term G g sits on the dark band, where the gain's I_a
    # varies most, and G g ≈ G there), so the depth of a crack 1.4 px wide (the far field of a
    # tilted camera) drowned in noise. The exposure, the local road's residual parallax and
    # the groove's depth all vary over centimetres, and the block is already the unit taken
    # as independent.
    cell = np.floor(raw / blk).astype(int)
    blk_of = np.unique(cell[:, 0] * 100003 + cell[:, 1], return_inverse=True)[1].ravel()
    n_blk = int(blk_of.max()) + 1
    for _ in range(cfg.groove_iterations):
        p = p0 + J * (D[:, None] * g + e[:, None])[..., None]
        pr = cam.distort_px(p.reshape(-1, 2)).reshape(p.shape)
        Ib = _sample(gb, pr)
        G = _sample(gx, pr) * J[..., 0] + _sample(gy, pr) * J[..., 1]  # intensity per metre
        # I_b + G g dD + G de = α I_a + β, least squares per block (its profiles' normal
        # equations summed)
        A = np.stack([G * g, G, -Ia, -np.ones_like(Ia)], axis=-1)
        fin = np.all(np.isfinite(A), axis=-1) & np.isfinite(Ib)
        ok &= fin.sum(axis=1) >= 0.9 * len(s)
        A = np.where(fin[..., None], A, 0.0)
        y = np.where(fin, -Ib, 0.0)
        N = np.zeros((n_blk, 4, 4))
        b = np.zeros((n_blk, 4))
        np.add.at(N, blk_of[ok], np.einsum("nki,nkj->nij", A[ok], A[ok]))
        np.add.at(b, blk_of[ok], np.einsum("nki,nk->ni", A[ok], y[ok]))
        try:
            x = np.linalg.solve(N + 1e-9 * np.eye(4), b[..., None])[..., 0][blk_of]
        except np.linalg.LinAlgError:
            return None
        lim = cfg.dense_max_depth_m
        D = np.clip(D + np.where(ok, x[:, 0], 0.0), -lim, lim)
        e = np.clip(e + np.where(ok, x[:, 1], 0.0), -lim, lim)
    # A floor beyond the bound is a failed fit (a slid profile, a shadow moving with the car).
    ok &= np.abs(D) < cfg.dense_max_depth_m
    if not ok.any():
        return None
    # The blocks' depths (their profiles share it), where at least half a block's profiles
    # were measured.
    cnt = np.bincount(blk_of[ok], minlength=n_blk)
    first = np.full(n_blk, -1)
    first[blk_of[ok][::-1]] = np.nonzero(ok)[0][::-1]
    blocks = D[first[cnt >= 0.5 * blk]]
    nb = len(blocks)
    if nb < cfg.groove_min_blocks:
        return None
    from scipy.stats import norm
    from scipy.stats import t as student_t

    mean = float(blocks.mean())
    sd = float(blocks.std(ddof=1))
    # Floor: LK's sub-pixel precision (0.02 px, as in crackdepth) over the motion across the
    # crack per metre of depth: a noiseless render is not exact.
    sd = max(sd, 0.02 / max(float(np.median(cj[ok])), 1e-9))
    t = mean / (sd / math.sqrt(nb))
    # The normal z of the same one-sided level: few blocks give a noisy spread (heavy tails).
    z = float(norm.isf(student_t.sf(abs(t), nb - 1))) * math.copysign(1.0, t)
    # (beyond float range, sf 0: far past any threshold; the normal reading then stands)
    ok_z = math.isfinite(z) and abs(t) > 1e-6 and abs(z) > 1e-6
    sig = sd * (t / z) if ok_z else sd
    return DenseCrack(blocks, sig, float(nb), 0.0)
