"""Locally fitted road surface and per-point residual height.

The road is modelled by heights at the nodes of a sparse anchor lattice (spacing
``local_fit_cell_m``), each from a robust plane (or quadric) fitted to the points inside a
``local_fit_window_m`` square window around the node; points that sit clearly below or above the
local road (potholes, cracks, kerbs) are trimmed iteratively (MAD-based, never tighter than
``local_fit_inlier_m``). The surface between nodes is bilinear, so it is continuous: there is no
step at window or pair boundaries. Only nodes near points exist (a hash, not a bounding box).
"""

from __future__ import annotations

import logging

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.core.geometry import check_shape
from roadsurf.mapping.config import MappingConfig

log = logging.getLogger(__name__)

_OFF = 1 << 20  # lattice index offset so keys stay positive
# nodes whose window sums are gathered at once: the (9, nodes, (2h)²) gather of a whole drive
# grew with its length (135 MB for 3,000 frames at h = 3); a block is ~10 MB at h = 3
_NODE_BLOCK = 4096


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
        self.cell = float(cfg.local_fit_cell_m)
        self.half = max(1, int(round(0.5 * cfg.local_fit_window_m / self.cell)))
        self.inlier_m = float(cfg.local_fit_inlier_m)
        self.origin = xyz[:, :2].min(0) if len(xyz) else np.zeros(2)
        self._fit(xyz, progress)

    def _fit(self, xyz: np.ndarray, progress: bool) -> None:
        """Vectorised robust fit: per-cell weighted moment sums, window sums per node by sparse
        lookups of the (2h)² neighbour cells, a 3×3 solve per node (plane z = c + a·dx + b·dy
        about the node), then trimming of points off the (bilinear) surface; 5 rounds."""
        c = self.cell
        self.node_keys = np.zeros(0, np.int64)
        self.node_z = np.zeros(0)
        if len(xyz) == 0:
            return
        rel = xyz[:, :2] - self.origin
        x, y = rel[:, 0], rel[:, 1]
        z0 = float(np.median(xyz[:, 2]))
        z = xyz[:, 2] - z0
        keys = _key(np.floor(x / c), np.floor(y / c))
        ukeys, inv = np.unique(keys, return_inverse=True)
        cix = ukeys // (1 << 22) - _OFF
        ciy = ukeys % (1 << 22) - _OFF
        nodes = np.unique(
            np.concatenate([_key(cix + dx, ciy + dy) for dx in (0, 1) for dy in (0, 1)])
        )
        nix = nodes // (1 << 22) - _OFF
        niy = nodes % (1 << 22) - _OFF
        xn, yn = nix * c, niy * c
        # neighbour cell index of each node for each window offset (-1: empty cell)
        h = self.half
        nb_a = np.empty((len(nodes), (2 * h) ** 2), np.int64)  # (nodes, (2h)²)
        for j, (dx, dy) in enumerate((dx, dy) for dx in range(-h, h) for dy in range(-h, h)):
            k = _key(nix + dx, niy + dy)
            pos = np.minimum(np.searchsorted(ukeys, k), len(ukeys) - 1)
            nb_a[:, j] = np.where(ukeys[pos] == k, pos, -1)
        terms = (np.ones_like(x), x, y, x * x, x * y, y * y, z, x * z, y * z)
        w = np.ones(len(x))
        self.node_keys = nodes
        self.node_z = np.full(len(nodes), np.nan)
        for _ in range(5):
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
            )[ok]
            rhs = np.stack([sz, XZ, YZ], -1)[ok]
            zn = np.full(len(nodes), np.nan)
            zn[ok] = np.linalg.solve(A, rhs[..., None])[:, 0, 0]
            self.node_z = zn
            fin = np.isfinite(zn)
            self.node_keys, self.node_z = nodes[fin], zn[fin]
            r = z - self._height_rel(rel)
            good = np.isfinite(r)
            if not good.any():
                break
            mad = (
                MAD_TO_SIGMA * float(np.median(np.abs(r[good & (w > 0)]))) if (w > 0).any() else 0.0
            )
            thr = max(3.0 * mad, self.inlier_m)
            w_new = (good & (np.abs(r) < thr)).astype(float)
            if np.array_equal(w_new, w):
                break
            w = w_new
        self.node_z = self.node_z + z0
        log.debug("road surface: %d nodes fitted", len(self.node_keys))

    # ------------------------------------------------------------------ evaluation
    def height(self, xy_enu_m: np.ndarray) -> np.ndarray:
        """(N, 2) ENU -> (N,) road height (m); NaN where no node around is fitted."""
        xy = np.atleast_2d(np.asarray(xy_enu_m, float))
        return self._height_rel(xy - self.origin)

    def _height_rel(self, rel: np.ndarray) -> np.ndarray:
        if len(self.node_keys) == 0:
            return np.full(len(rel), np.nan)
        xy = rel
        g = rel / self.cell
        i0 = np.floor(g[:, 0]).astype(np.int64)
        j0 = np.floor(g[:, 1]).astype(np.int64)
        fx, fy = g[:, 0] - i0, g[:, 1] - j0
        num = np.zeros(len(xy))
        den = np.zeros(len(xy))
        for di, dj, w in (
            (0, 0, (1 - fx) * (1 - fy)),
            (1, 0, fx * (1 - fy)),
            (0, 1, (1 - fx) * fy),
            (1, 1, fx * fy),
        ):
            k = _key(i0 + di, j0 + dj)
            pos = np.searchsorted(self.node_keys, k)
            pos = np.minimum(pos, len(self.node_keys) - 1)
            hit = self.node_keys[pos] == k
            num[hit] += w[hit] * self.node_z[pos[hit]]
            den[hit] += w[hit]
        out = np.full(len(xy), np.nan)
        ok = den > 1e-6
        out[ok] = num[ok] / den[ok]
        return out

    def residual(self, xyz_enu_m: np.ndarray) -> np.ndarray:
        """(N, 3) ENU points -> (N,) signed height above the local road (m, negative below)."""
        xyz = check_shape("xyz_enu_m", np.asarray(xyz_enu_m, float), (None, 3))
        return xyz[:, 2] - self.height(xyz[:, :2])
