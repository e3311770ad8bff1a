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
from tqdm import tqdm

from mapping.config import MappingConfig
from roadsurf.geometry import check_shape

log = logging.getLogger(__name__)

_OFF = 1 << 20  # lattice index offset so keys stay positive


def _key(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    return (np.asarray(ix, np.int64) + _OFF) * (1 << 22) + (np.asarray(iy, np.int64) + _OFF)


class LocalSurface:
    """Road height z_road(x, y) in ENU (metres) from robust local fits."""

    def __init__(self, cfg: MappingConfig, xyz_enu_m: np.ndarray, progress: bool = True) -> None:
        xyz = check_shape("xyz_enu_m", np.asarray(xyz_enu_m, float), (None, 3))
        self.cell = float(cfg.local_fit_cell_m)
        self.half = max(1, int(round(0.5 * cfg.local_fit_window_m / self.cell)))
        self.inlier_m = float(cfg.local_fit_inlier_m)
        self.order = int(cfg.local_fit_order)
        self.origin = xyz[:, :2].min(0) if len(xyz) else np.zeros(2)
        self._fit(xyz, progress)

    def _fit(self, xyz: np.ndarray, progress: bool) -> None:
        c = self.cell
        if len(xyz) == 0:
            self.node_keys = np.zeros(0, np.int64)
            self.node_z = np.zeros(0)
            return
        rel = xyz[:, :2] - self.origin
        ix = np.floor(rel[:, 0] / c).astype(np.int64)
        iy = np.floor(rel[:, 1] / c).astype(np.int64)
        keys = _key(ix, iy)
        order = np.argsort(keys, kind="stable")
        skeys = keys[order]
        ukeys, starts = np.unique(skeys, return_index=True)
        ends = np.append(starts[1:], len(skeys))
        cell_rng = dict(
            zip(ukeys.tolist(), zip(starts.tolist(), ends.tolist(), strict=True), strict=True)
        )
        pts = xyz[order]
        # nodes: corners of occupied cells
        cix = ukeys // (1 << 22) - _OFF
        ciy = ukeys % (1 << 22) - _OFF
        nodes = np.unique(
            np.concatenate([_key(cix + dx, ciy + dy) for dx in (0, 1) for dy in (0, 1)])
        )
        nix = nodes // (1 << 22) - _OFF
        niy = nodes % (1 << 22) - _OFF
        z = np.full(len(nodes), np.nan)
        h = self.half
        span = range(-h, h)
        max_pts = 4000
        it = tqdm(
            range(len(nodes)),
            desc="road surface fit",
            unit="node",
            disable=not progress,
            leave=False,
        )
        for j in it:
            chunks = []
            for dx in span:
                for dy in span:
                    r = cell_rng.get(int(_key(nix[j] + dx, niy[j] + dy)))
                    if r is not None:
                        chunks.append(pts[r[0] : r[1]])
            if not chunks:
                continue
            P = np.concatenate(chunks) if len(chunks) > 1 else chunks[0]
            if len(P) < 8:
                continue
            if len(P) > max_pts:
                P = P[:: int(np.ceil(len(P) / max_pts))]
            node_xy = self.origin + np.array([nix[j], niy[j]], float) * c
            z[j] = self._robust_fit(P, node_xy)
        ok = np.isfinite(z)
        self.node_keys = nodes[ok]
        self.node_z = z[ok]
        log.debug("road surface: %d nodes fitted of %d", ok.sum(), len(nodes))

    def _robust_fit(self, P: np.ndarray, node_xy: np.ndarray) -> float:
        dx, dy = P[:, 0] - node_xy[0], P[:, 1] - node_xy[1]
        cols = [np.ones(len(P)), dx, dy]
        if self.order >= 2:
            cols += [dx * dx, dx * dy, dy * dy]
        A = np.column_stack(cols)
        z = P[:, 2]
        inl = np.ones(len(P), bool)
        coef = None
        for _ in range(5):
            if inl.sum() < A.shape[1] + 3:
                break
            coef, *_ = np.linalg.lstsq(A[inl], z[inl], rcond=None)
            r = z - A @ coef
            s = 1.4826 * np.median(np.abs(r[inl]))
            thr = max(3.0 * s, self.inlier_m)
            new = np.abs(r) < thr
            if np.array_equal(new, inl):
                break
            inl = new
        return float(coef[0]) if coef is not None else float("nan")

    # ------------------------------------------------------------------ evaluation
    def height(self, xy_enu_m: np.ndarray) -> np.ndarray:
        """(N, 2) ENU -> (N,) road height (m); NaN where no node around is fitted."""
        xy = np.atleast_2d(np.asarray(xy_enu_m, float))
        if len(self.node_keys) == 0:
            return np.full(len(xy), np.nan)
        g = (xy - self.origin) / self.cell
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
