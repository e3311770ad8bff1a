"""Per-cell pieces of the dense surface (``mapping.dense_fuse``), pure functions of arrays.

- ``cell_samples``: one pair's height at ground cells, by a ray fixed point through image a,
  with the visibility test (``MappingConfig.dense_visible_k``) and the pixel's variance
  widened by its ground footprint.
- ``fuse_cells``: the pairs' samples fused per cell (variance-weighted median, then the mean of
  those within a few σ).

No I/O and no state: a Ray task or a GPU port can call them on a tile's arrays.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np

# bump when the dense matching (reconstruction/dense: matching, warp, checks, parallax) or this
# fusion changes what a cell's height is: a resumed run then matches again (the map stage's
# fingerprint holds it). 2: the overlap-edge windows (5439d92), the visibility test and the
# valid-only sampling; 3: the sweep's minimum samples per candidate (session 24); 4: the
# slanted second pass (dense.slanted) and the ray fixed point run to convergence; 5: the
# sweep's unscored band along the overlap's edge starts from its swept neighbours; 6: the
# shifted windows, the step test and no coarse fill of left-right or step refusals; 7: a
# rolling-shutter pair measured on image b
DENSE_SURFACE_VERSION = 11  # 8: the sweep's pixels outside the overlap start from its neighbours;
# 9: the single-view fill judges relief on a 5 x 5 block (rasterfill.RELIEF_BLOCK_HALF); 10:
# cloud.ply heights ellipsoidal (GridToEnu.height_lift: the tangent plane's rise, d² / 2R);
# 11: a hole across a pothole wall ramps from rim to floor (rasterfill.fill_inward)
FIXED_POINT_STEPS = 3  # cell -> pixel projections at the sampled height (nadir: 2 suffice)
# ... then, on the cells whose last step moved by more than FIXED_POINT_TOL_M, up to this
# many in all (a cell still jumping by FIXED_POINT_FLIP_M then keeps its FIXED_POINT_STEPS
# result): on a wall
# facing a tilted camera the step only shrinks by c = s tanθ / (1 + s tanθ) per step (slope
# 1.5 at 45°: 0.6; 3 steps leave 22 % of the start's error). Seed-7 45° stereo pair with the
# matching replaced by the exact heights: pothole RMS 1.37 -> 1.00 mm, cells steeper than 1
# read +2.2 -> +0.9 mm shallow (12 steps everywhere)
FIXED_POINT_MAX_STEPS = 16
REMAP_COLS = 1024  # the moving cells' layout for cv2.remap (cells per row)
FIXED_POINT_TOL_M = 1e-4  # a tenth of a millimetre: well below a cell's height σ (m)
# a step this large after FIXED_POINT_MAX_STEPS is no convergence but a flip between two
# surfaces (m): above the matching's noise on a wall (per-pixel σ 1-4 mm, a cycle's steps a
# fraction of it), below a pothole's depth
FIXED_POINT_FLIP_M = 0.005
MEDIAN_START_PX = 5  # the second pass starts from this median of the first (cells)


class _PlaneModel(Protocol):
    @property
    def K(self) -> np.ndarray: ...  # (3, 3) intrinsics of the height map's grid

    @property
    def n(self) -> np.ndarray: ...  # (3,) the pair's road normal in camera a

    @property
    def h_a(self) -> float: ...  # camera a's distance to the road plane (m)


def cell_samples(
    model: _PlaneModel,
    R: np.ndarray,
    C: np.ndarray,
    height_filled: np.ndarray,
    valid_f: np.ndarray,
    var_px: np.ndarray,
    e: np.ndarray,
    n: np.ndarray,
    z: np.ndarray,
    gsd_m: float,
    visible_k: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One pair's height at cells (e, n) (ENU m, any shape S) whose road lies at ENU height z.

    ``model``: the pair's plane + parallax model (K, road normal n, distance h_a in camera a);
    ``R`` (3, 3) ENU from camera a, ``C`` (3,) its centre (m); ``height_filled``, ``valid_f``,
    ``var_px`` (h, w) float32: the height map (m, 0 where invalid), 1 where valid, its variance
    (m², 0 where invalid). Returns (ok (S,) bool, r (S,) height above z (m), var (S,) m²) or None.

    A cell projected at height z + r into image a reads the height η the pixel there saw, and r
    becomes the height of that pixel's point (a ray cast). On a slope s along the view the step
    converges as c^k, c = s tanθ / (1 + s tanθ) (θ the ray's angle from vertical, c = 0 on flat
    road). With ``visible_k`` > 0 the sample counts only where the point the last pixel sees
    lies within visible_k x max(the pixel's ground footprint, the cell) of the cell's centre: a
    tilted camera cannot see a steep pothole's wall on its own side, and those cells took the
    floor seen past the rim; and the fixed point runs again from the local median of its first
    pass (a rough floor 70 mm down is left a few mm off by 3 steps from the road).
    """
    K, nrm, ha = model.K, model.n, model.h_a
    # camera-a coordinates of the cell at height z + r: the horizontal part is fixed, only
    # the third row of R moves with the height (X = Rᵀ (P - C))
    X0 = (e - C[0]) * R[0, 0] + (n - C[1]) * R[1, 0]
    X1 = (e - C[0]) * R[0, 1] + (n - C[1]) * R[1, 1]
    X2 = (e - C[0]) * R[0, 2] + (n - C[1]) * R[1, 2]
    # a pixel's ray r = K⁻¹ (u, v, 1) reaches height η above the pair's plane at depth
    # (h_a - η) / n·r, i.e. at ENU height C_z + (h_a - η) (R₂·r) / (n·r): both dot products
    # are linear in u, v
    Ki = np.linalg.inv(K)
    a = R[2] @ Ki
    b = nrm @ Ki

    def step(r: np.ndarray, sel: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """One step r <- (height the ray through (cell, r) sees) for the cells ``sel`` (a
        flat index array; None: all, in their own shape)."""
        if sel is None:
            zz, x0, x1, x2 = z, X0, X1, X2
        else:  # cv2.remap wants 2D maps under 32767 x 32767: rows of REMAP_COLS, padded
            pad = -len(sel) % REMAP_COLS

            def rows(x: np.ndarray) -> np.ndarray:
                return np.pad(x, (0, pad), mode="edge").reshape(-1, REMAP_COLS)

            zz, x0, x1, x2 = (rows(q.reshape(-1)[sel]) for q in (z, X0, X1, X2))
            r = rows(r)
        dz = zz + r - C[2]
        Z = x2 + dz * R[2, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            Z = np.where(Z > 1e-6, Z, np.nan)
            u = K[0, 0] * (x0 + dz * R[2, 0]) / Z + K[0, 2]
            v = K[1, 1] * (x1 + dz * R[2, 1]) / Z + K[1, 2]
        uf = np.nan_to_num(u, nan=-10).astype(np.float32)
        vf = np.nan_to_num(v, nan=-10).astype(np.float32)
        # bilinear over the valid neighbours only (a pixel next to an invalid one keeps its
        # value; wv: the share of the weight on valid pixels)
        wv = cv2.remap(valid_f, uf, vf, cv2.INTER_LINEAR, borderValue=0)
        eta = cv2.remap(height_filled, uf, vf, cv2.INTER_LINEAR, borderValue=0)
        eta = eta / np.maximum(wv, 1e-3)
        with np.errstate(invalid="ignore", divide="ignore"):
            pz = C[2] + (ha - eta) * (a[0] * u + a[1] * v + a[2]) / (b[0] * u + b[1] * v + b[2])
        out = (pz - zz, u, v, uf, vf, eta, Z, wv)
        return out if sel is None else tuple(x.reshape(-1)[: len(sel)] for x in out)

    def ray_steps(r: np.ndarray) -> tuple[np.ndarray, ...]:
        """FIXED_POINT_STEPS steps on every cell, then up to FIXED_POINT_MAX_STEPS on those
        whose last step moved by more than FIXED_POINT_TOL_M. A cell whose last step then
        still exceeds FIXED_POINT_FLIP_M (a hidden wall: its ray flips between the rim and
        the floor past it) keeps its FIXED_POINT_STEPS result."""
        r0 = r
        for _ in range(FIXED_POINT_STEPS):
            r0 = r
            r, u, v, uf, vf, eta, Z, wv = step(r, None)
        outs = [r, u, v, uf, vf, eta, Z, wv]
        with np.errstate(invalid="ignore"):
            moving = np.flatnonzero(np.abs(r - r0) > FIXED_POINT_TOL_M)
        if moving.size == 0:
            return tuple(outs)
        flat = [x.reshape(-1) for x in outs]  # views: writes land in outs
        first = [f[moving] for f in flat]
        left, last = moving, np.zeros(0)
        for _ in range(FIXED_POINT_STEPS, FIXED_POINT_MAX_STEPS):
            if left.size == 0:
                break
            got = step(flat[0][left], left)
            with np.errstate(invalid="ignore"):
                d = np.abs(got[0] - flat[0][left])
                still = d > FIXED_POINT_TOL_M
            for f, g in zip(flat, got, strict=True):
                f[left] = g
            left, last = left[still], d[still]
        back = np.isin(moving, left[last > FIXED_POINT_FLIP_M])
        for f, g in zip(flat, first, strict=True):
            f[moving[back]] = g[back]
        return tuple(outs)

    r, u, v, uf, vf, eta, Z, wv = ray_steps(np.zeros_like(z))
    if visible_k > 0:
        start = cv2.medianBlur(np.nan_to_num(r, nan=0.0).astype(np.float32), MEDIAN_START_PX)
        r, u, v, uf, vf, eta, Z, wv = ray_steps(start.astype(r.dtype))
    ok = (wv >= 0.5) & np.isfinite(r)  # at least half the bilinear weight on valid pixels
    # ground footprint of the pixel vs the cell: a coarser view weighs less
    rx, ry = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(rx * nrm[0] + ry * nrm[1] + nrm[2]) / np.sqrt(rx * rx + ry * ry + 1.0)
        foot = Z / K[0, 0] / np.sqrt(np.maximum(cos, 0.1))
        if visible_k > 0:
            # the point the last pixel sees, horizontally from the cell's centre
            depth = (ha - eta) / (b[0] * u + b[1] * v + b[2])
            ex, nx = R[0] @ Ki, R[1] @ Ki
            de = C[0] + depth * (ex[0] * u + ex[1] * v + ex[2]) - e
            dn = C[1] + depth * (nx[0] * u + nx[1] * v + nx[2]) - n
            ok &= np.hypot(de, dn) <= visible_k * np.maximum(foot, gsd_m)
    if not ok.any():
        return None
    var = cv2.remap(var_px, uf, vf, cv2.INTER_LINEAR, borderValue=0) / np.maximum(wv, 1e-3)
    with np.errstate(invalid="ignore"):
        var = var.astype(float) * np.maximum(1.0, (foot / gsd_m) ** 2)
    return ok, r, var


def fuse_cells(
    cell: np.ndarray, value: np.ndarray, var: np.ndarray, n_cells: int, outlier_sigmas: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust variance-weighted estimate per cell from samples (N,) of ``value`` with variance
    ``var`` in cells ``cell`` (0..n_cells-1): the weighted median m, then the weighted mean of
    the samples within ``outlier_sigmas`` x their σ (+ 0.2 mm) of m. Returns (n_cells,) float32
    estimate (NaN where empty), int32 count of the samples kept and float32 σ of the estimate:
    sqrt(1 / Σw), or the weighted scatter / sqrt(count) when the samples disagree more."""
    est = np.full(n_cells, np.nan, np.float32)
    cnt = np.zeros(n_cells, np.int32)
    sig = np.full(n_cells, np.nan, np.float32)
    ok = np.isfinite(value) & np.isfinite(var) & (var > 0)
    if not ok.any():
        return est, cnt, sig
    c, v, s2 = cell[ok].astype(np.int64), value[ok].astype(float), var[ok].astype(float)
    w = 1.0 / s2
    order = np.lexsort((v, c))
    c, v, w, s2 = c[order], v[order], w[order], s2[order]
    starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    ids = c[starts]
    cw = np.cumsum(w)
    before = np.r_[0.0, cw[:-1]][starts]  # cumulative weight before each group
    tot = np.add.reduceat(w, starts)
    grp = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(c)]))
    # the first sample of each group whose cumulative weight reaches half the group's weight
    half = (cw - before[grp]) >= 0.5 * tot[grp]
    first = np.flatnonzero(half & np.r_[True, ~half[:-1] | (grp[1:] != grp[:-1])])
    med = np.empty(len(starts))
    med[grp[first]] = v[first]
    keep = np.abs(v - med[grp]) <= outlier_sigmas * np.sqrt(s2) + 2e-4
    kw = np.where(keep, w, 0.0)
    sw = np.bincount(grp, kw, len(starts))
    mean = np.bincount(grp, kw * v, len(starts)) / np.maximum(sw, 1e-300)
    scatter = np.bincount(grp, kw * (v - mean[grp]) ** 2, len(starts)) / np.maximum(sw, 1e-300)
    n = np.bincount(grp, keep, len(starts))
    has = sw > 0
    est[ids[has]] = mean[has]
    cnt[ids[has]] = n[has]
    sd = np.sqrt(np.maximum(1.0 / np.maximum(sw, 1e-300), scatter / np.maximum(n, 1)))
    sig[ids[has]] = sd[has]
    return est, cnt, sig
