"""Locally fitted road surface and per-point residual height.

The road is modelled by heights at the nodes of a sparse anchor lattice (spacing
``local_fit_cell_m``), each from a robust plane fitted to the points inside a
``local_fit_window_m`` square window around the node; points that sit clearly below or above the
local road (potholes, cracks, kerbs) are trimmed iteratively (MAD-based, never tighter than
``local_fit_inlier_m``; the threshold starts wide and halves each round, so a fit that a large
defect pulled down is walked back to the majority). A pothole wider than the window fills some
windows whole, so a coarse fit over ``local_fit_bridge_m`` (4 m) comes first: the local fit
starts from the points near it, and holds its plane as a prior worth a few points, which decides
only where a window holds little road. (A gate keeping points far below the coarse plane out,
and a prior worth 2 % of a window's points, bridged 1-3 mm better but read a 4 % sag or a V
gutter as a 1.6-2.2 m² depression 30-50 mm deep: not kept.) The surface between nodes is
bilinear, so it is continuous: there is no step at window or pair boundaries. Only nodes near
points exist (a hash, not a bounding box). Points with a NaN coordinate are left out.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.core.geometry import check_shape
from roadsurf.mapping.config import MappingConfig

log = logging.getLogger(__name__)

_OFF = 1 << 20  # lattice index offset so keys stay positive
# nodes whose window sums are gathered at once: the (9, nodes, (2h)²) gather of a whole drive
# grew with its length (135 MB for 3,000 frames at h = 3); a block is ~10 MB at h = 3
_NODE_BLOCK = 4096
_ROUNDS = 8  # trimming rounds of one lattice fit
_PRIOR_POINTS = 8.0  # weight of the coarse plane in each local fit (points spread over the window)
_ANNEAL_START = 8.0  # the first trimming threshold, in local_fit_inlier_m (64 mm by default)


def _key(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    return (np.asarray(ix, np.int64) + _OFF) * (1 << 22) + (np.asarray(iy, np.int64) + _OFF)


def _window_sums(cell: np.ndarray, nb: np.ndarray, block: int = _NODE_BLOCK) -> np.ndarray:
    """``cell[:, nb].sum(axis=2)`` (cell (T, C + 1) sums per cell, nb (nodes, K) cell indices;
    -1 the zero column) -> (T, nodes), gathered ``block`` nodes at a time so the (T, nodes, K)
    gather never exists whole; each node's sum is the same reduction, so the same bits."""
    out = np.empty((cell.shape[0], len(nb)))
    for i in range(0, len(nb), block):
        out[:, i : i + block] = cell[:, nb[i : i + block]].sum(axis=2)
    return out


class LocalSurface:
    """Road height z_road(x, y) in ENU (metres) from robust local fits."""

    def __init__(self, cfg: MappingConfig, xyz_enu_m: np.ndarray, progress: bool = True) -> None:
        xyz = check_shape("xyz_enu_m", np.asarray(xyz_enu_m, float), (None, 3))
        xyz = xyz[np.all(np.isfinite(xyz), axis=1)]  # one NaN made the median, and all, NaN
        self.cell = float(cfg.local_fit_cell_m)
        self.half = max(1, int(round(0.5 * cfg.local_fit_window_m / self.cell)))
        self.inlier_m = float(cfg.local_fit_inlier_m)
        self.origin = xyz[:, :2].min(0) if len(xyz) else np.zeros(2)
        self.node_keys = np.zeros(0, np.int64)
        self.node_z = np.zeros(0)
        if len(xyz) == 0:
            return
        rel = xyz[:, :2] - self.origin
        z0 = float(np.median(xyz[:, 2]))
        z = xyz[:, 2] - z0
        w0 = np.ones(len(z))
        start = _ANNEAL_START * self.inlier_m
        coarse: _Lattice | None = None
        bridge = float(cfg.local_fit_bridge_m)
        if bridge > cfg.local_fit_window_m:
            # A defect wider than the local window fills some windows: fitted alone they follow
            # its floor. A coarse fit over `bridge` spans it; the local fit starts from the
            # points near the coarse road and holds its plane as a prior of a few points.
            coarse = _fit_lattice(rel, z, bridge / (2 * self.half), self.half, self.inlier_m,
                                  w0, start, None)  # fmt: skip
            rc = z - coarse.height(rel)
            w0 = np.where(np.isfinite(rc), np.abs(rc) < coarse.thr, True).astype(float)
            start = coarse.thr
        fine = _fit_lattice(rel, z, self.cell, self.half, self.inlier_m, w0, start, coarse)
        self.node_keys, self.node_z = fine.keys, fine.z + z0
        log.debug("road surface: %d nodes fitted", len(self.node_keys))

    # ------------------------------------------------------------------ evaluation
    def height(self, xy_enu_m: np.ndarray) -> np.ndarray:
        """(N, 2) ENU -> (N,) road height (m); NaN where no node around is fitted."""
        xy = np.atleast_2d(np.asarray(xy_enu_m, float))
        return _bilinear(xy - self.origin, self.cell, self.node_keys, self.node_z)

    def residual(self, xyz_enu_m: np.ndarray) -> np.ndarray:
        """(N, 3) ENU points -> (N,) signed height above the local road (m, negative below)."""
        xyz = check_shape("xyz_enu_m", np.asarray(xyz_enu_m, float), (None, 3))
        return xyz[:, 2] - self.height(xyz[:, :2])


@dataclass(frozen=True)
class _Lattice:
    """Node heights of one lattice fit (relative xy and z) and its final trimming threshold."""

    cell: float  # node spacing (m)
    keys: np.ndarray  # (K,) int64 node keys, sorted
    z: np.ndarray  # (K,) node heights (m)
    thr: float  # points within this of the fit were road in its last round (m)

    def height(self, rel: np.ndarray) -> np.ndarray:
        return _bilinear(rel, self.cell, self.keys, self.z)


def _fit_lattice(
    rel: np.ndarray,
    z: np.ndarray,
    c: float,
    h: int,
    inlier_m: float,
    w0: np.ndarray,
    start_m: float,
    fallback: _Lattice | None,
) -> _Lattice:
    """Vectorised robust fit on a lattice of spacing ``c`` (m): per-cell weighted moment sums,
    window sums per node by sparse lookups of the (2h)² neighbour cells, a 3×3 solve per node
    (plane z = c + a·dx + b·dy about the node), then trimming of points off the (bilinear)
    surface. The trimming threshold starts at ``start_m`` and halves each round down to
    max(3 MAD, ``inlier_m``) (graduated: a least-squares start that a large pothole pulled down
    is walked back to the majority, the road, instead of being frozen by a wide MAD). rel (N, 2)
    and z (N,) in metres, w0 (N,) the start weights (0/1); ``fallback``'s plane is a weak prior
    on each node (``_plane_prior``: it decides only where the window holds few road points)."""
    x, y = rel[:, 0], rel[:, 1]
    keys = _key(np.floor(x / c), np.floor(y / c))
    ukeys, inv = np.unique(keys, return_inverse=True)
    cix = ukeys // (1 << 22) - _OFF
    ciy = ukeys % (1 << 22) - _OFF
    nodes = np.unique(np.concatenate([_key(cix + dx, ciy + dy) for dx in (0, 1) for dy in (0, 1)]))
    nix = nodes // (1 << 22) - _OFF
    niy = nodes % (1 << 22) - _OFF
    xn, yn = nix * c, niy * c
    # neighbour cell index of each node for each window offset (-1: empty cell)
    nb_a = np.empty((len(nodes), (2 * h) ** 2), np.int64)  # (nodes, (2h)²)
    for j, (dx, dy) in enumerate((dx, dy) for dx in range(-h, h) for dy in range(-h, h)):
        k = _key(nix + dx, niy + dy)
        pos = np.minimum(np.searchsorted(ukeys, k), len(ukeys) - 1)
        nb_a[:, j] = np.where(ukeys[pos] == k, pos, -1)
    terms = (np.ones_like(x), x, y, x * x, x * y, y * y, z, x * z, y * z)
    prior = None if fallback is None else _plane_prior(fallback, xn, yn, c, h)
    w = np.asarray(w0, float)
    anneal = float(start_m)
    out_keys, out_z, thr = nodes[:0], np.zeros(0), float(inlier_m)
    for _ in range(_ROUNDS):
        cell = np.stack([np.bincount(inv, weights=w * t, minlength=len(ukeys)) for t in terms])
        cell = np.concatenate([cell, np.zeros((len(terms), 1))], axis=1)  # index -1 = empty
        S = _window_sums(cell, nb_a)  # (9, nodes)
        n, sx, sy, sxx, sxy, syy, sz, sxz, syz = S
        # moments about the node
        X, Y = sx - n * xn, sy - n * yn
        XX = sxx - 2 * xn * sx + n * xn * xn
        XY = sxy - xn * sy - yn * sx + n * xn * yn
        YY = syy - 2 * yn * sy + n * yn * yn
        XZ, YZ = sxz - xn * sz, syz - yn * sz
        ok = n >= 8
        ridge = 1e-6 * np.maximum(n, 1.0)  # keeps slopes finite on a narrow strip
        A = np.stack(
            [
                np.stack([n, X, Y], -1),
                np.stack([X, XX + ridge, XY], -1),
                np.stack([Y, XY, YY + ridge], -1),
            ],
            axis=1,
        )
        rhs = np.stack([sz, XZ, YZ], -1)
        if prior is not None:  # the coarse plane as a few pseudo-points: a window whose road
            pA, prhs = prior  # is one strip at its edge does not extrapolate a free slope
            A, rhs = A + pA, rhs + prhs
            ok |= pA[:, 0, 0] > 0
        zn = np.full(len(nodes), np.nan)
        zn[ok] = np.linalg.solve(A[ok], rhs[ok][..., None])[:, 0, 0]
        fin = np.isfinite(zn)
        out_keys, out_z = nodes[fin], zn[fin]
        r = z - _bilinear(rel, c, out_keys, out_z)
        good = np.isfinite(r)
        if not good.any():
            break
        used = good & (w > 0)
        mad = MAD_TO_SIGMA * float(np.median(np.abs(r[used]))) if used.any() else 0.0
        floor = max(3.0 * mad, inlier_m)
        thr = max(floor, anneal)
        w_new = (good & (np.abs(r) < thr)).astype(float)
        if np.array_equal(w_new, w) and anneal <= floor:
            break
        w = w_new
        anneal *= 0.5
    return _Lattice(c, out_keys, out_z, thr)


def _plane_prior(
    coarse: _Lattice,
    xn: np.ndarray,
    yn: np.ndarray,
    c: float,
    h: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The coarse fit's plane at each node (height and slopes) as normal-equation terms
    ((nodes, 3, 3), (nodes, 3)) worth ``_PRIOR_POINTS`` points spread over the window; zero
    where the coarse fit has no height."""
    at = np.column_stack([xn, yn])
    zc = coarse.height(at)
    ac = (coarse.height(at + [c, 0.0]) - coarse.height(at - [c, 0.0])) / (2 * c)
    bc = (coarse.height(at + [0.0, c]) - coarse.height(at - [0.0, c])) / (2 * c)
    lam = _PRIOR_POINTS
    has = np.isfinite(zc) & np.isfinite(ac) & np.isfinite(bc)
    lam_n = np.where(has, lam, 0.0)
    s2 = (h * c) ** 2 / 3.0  # variance of a coordinate spread evenly over the window
    pA = np.zeros((len(xn), 3, 3))
    pA[:, 0, 0] = lam_n
    pA[:, 1, 1] = pA[:, 2, 2] = lam_n * s2
    prhs = np.column_stack([lam_n * np.nan_to_num(zc), lam_n * s2 * np.nan_to_num(ac),
                            lam_n * s2 * np.nan_to_num(bc)])  # fmt: skip
    return pA, prhs


def _bilinear(rel: np.ndarray, cell: float, keys: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """Bilinear height at relative xy (N, 2) from the lattice nodes (keys, zs); NaN where no
    node around has a height, or xy is not finite."""
    if len(keys) == 0:
        return np.full(len(rel), np.nan)
    g = np.where(np.isfinite(rel), rel, 0.0) / cell  # (NaN rows: no key, read NaN below)
    i0 = np.floor(g[:, 0]).astype(np.int64)
    j0 = np.floor(g[:, 1]).astype(np.int64)
    fx, fy = g[:, 0] - i0, g[:, 1] - j0
    num = np.zeros(len(rel))
    den = np.zeros(len(rel))
    for di, dj, w in (
        (0, 0, (1 - fx) * (1 - fy)),
        (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy),
    ):
        k = _key(i0 + di, j0 + dj)
        pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
        hit = keys[pos] == k
        num[hit] += w[hit] * zs[pos[hit]]
        den[hit] += w[hit]
    out = np.full(len(rel), np.nan)
    ok = (den > 1e-6) & np.all(np.isfinite(rel), axis=1)
    out[ok] = num[ok] / den[ok]
    return out
