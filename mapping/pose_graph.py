"""The robust pose graph: sparse least squares over every frame pose with relative (pair),
GPS position and heading (eq. 6.1), OBD speed, tilt and constant-velocity constraints, solved by
Levenberg-Marquardt with a robust loss, then GPS σ re-scaling and outlier rejection."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

from roadsurf.core.fits import RAYLEIGH_MEDIAN
from roadsurf.core.geometry import (
    forward_in_cam,
    heading_deg_from_displacement,
    invert_pose,
)
from roadsurf.io.drive import Drive
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.grade import up_axes_in_cam
from roadsurf.mapping.pose_gps import GpsFixes, interp_weights
from roadsurf.mapping.types import PoseReport
from roadsurf.reconstruction.consensus import plane_normal_cam

if TYPE_CHECKING:
    from collections.abc import Sequence

    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


# a fix the visual consensus left out (mapping.gps_consensus: at least 0.3 m off) rejoins only
# when the solution comes this close to it (m)
HELD_READMIT_M = 0.15


def _robust_weights(r: np.ndarray, loss: str, c: float) -> np.ndarray:
    """IRLS weights w(r) = ρ'(r²)/1 for the named robust loss with scale c (σ units)."""
    z = (r / c) ** 2
    if loss == "cauchy":
        return 1.0 / (1.0 + z)
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1e-300)))
    if loss == "arctan":
        return 1.0 / (1.0 + z**2)
    return np.ones_like(r)


def _robust_cost(r: np.ndarray, loss: str, c: float) -> float:
    z = (r / c) ** 2
    if loss == "cauchy":
        rho = np.log1p(z)
    elif loss == "soft_l1":
        rho = 2.0 * (np.sqrt(1.0 + z) - 1.0)
    elif loss == "huber":
        rho = np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0)
    elif loss == "arctan":
        rho = np.arctan(z)
    else:
        rho = z
    return float(0.5 * c * c * np.sum(rho))


def _color_columns(S: sp.csr_matrix) -> np.ndarray:
    """Greedy colouring of columns so that no two columns of one colour share a row."""
    C = (S.T.astype(np.int32) @ S.astype(np.int32)).tocsr()
    n = S.shape[1]
    colors = -np.ones(n, int)
    for j in range(n):
        used = set(colors[C.indices[C.indptr[j] : C.indptr[j + 1]]].tolist())
        k = 0
        while k in used:
            k += 1
        colors[j] = k
    return colors


class PoseGraph:
    """Sparse robust least squares over x = [φ_i (3), p_i (3)] per frame, with
    R_i = Exp(φ_i) R0_i and p_i the camera centre in ENU."""

    def __init__(
        self,
        cfg: MappingConfig,
        t: np.ndarray,
        init: np.ndarray,
        ok_pairs: list[PairResult],
        pos_of: dict[int, int],
        gps: GpsFixes | None,
        drive: Drive,
        comp: np.ndarray,
        R_vehicle_from_cam: np.ndarray | None = None,
        grade_rad: np.ndarray | None = None,
        still: Sequence[PairResult] = (),
        gps_used: np.ndarray | None = None,
    ) -> None:
        """``gps_used`` (G,) bool: the fixes of the first solve (None: all). The outlier test
        after it judges every fix again; one left out here (off the visual consensus,
        ``mapping.gps_consensus``) comes back only within ``HELD_READMIT_M`` of the solution:
        the test's 5 σ of an RTK log's HDOP-based σ is 2 m."""
        self.cfg, self.t, self.n = cfg, t, len(t)
        R_vc = np.eye(3) if R_vehicle_from_cam is None else np.asarray(R_vehicle_from_cam, float)
        self.fwd_cam = forward_in_cam(R_vc)  # the vehicle's forward axis in camera coordinates
        self.R0 = Rotation.from_matrix(init[:, :3, :3])
        self.p0 = init[:, :3, 3].copy()
        self.gps = gps
        self.gps_used = np.ones(0 if gps is None else len(gps.t_s), bool)
        self.gps_held = np.zeros_like(self.gps_used)
        if gps is not None and gps_used is not None:
            self.gps_used = np.asarray(gps_used, bool).copy()
            self.gps_held = ~self.gps_used
        self.gps_scale = 1.0
        self.vis_scale = 1.0

        # relative constraints: ok pairs + constant-velocity guesses across failed pairs
        ia, ib, Rm, tm, st, sr = [], [], [], [], [], []
        for p in ok_pairs:
            a, b = pos_of[p.index_a], pos_of[p.index_b]
            T = p.cam_b_from_cam_a
            ia.append(a), ib.append(b), Rm.append(T[:3, :3]), tm.append(T[:3, 3])
            st.append(
                cfg.visual_sigma_trans_m + cfg.visual_sigma_trans_rel * np.linalg.norm(T[:3, 3])
            )
            sr.append(math.radians(cfg.visual_sigma_rot_deg))
        self.n_vis = len(ia)
        # frames a stopped vehicle took (``no_motion`` pairs): each at the pose of the stop's
        # first frame, at the visual σ (a star, not a chain: a chain of N zero motions would
        # let the stop wander by √N σ); after n_vis, since their zero residuals would shrink
        # the visual σ's robust rescaling
        anchor: dict[int, int] = {}
        for a, b in sorted((pos_of[p.index_a], pos_of[p.index_b]) for p in still):
            anchor[b] = anchor.get(a, a)
            ia.append(anchor[b]), ib.append(b), Rm.append(np.eye(3)), tm.append(np.zeros(3))
            st.append(cfg.visual_sigma_trans_m), sr.append(math.radians(cfg.visual_sigma_rot_deg))
        for i in range(self.n - 1):
            if comp[i] != comp[i + 1]:
                # the initial guess already holds the best motion across the gap (chained
                # constant velocity, or the GPS track when vision broke)
                T = invert_pose(init[i + 1]) @ init[i]
                ia.append(i), ib.append(i + 1), Rm.append(T[:3, :3]), tm.append(T[:3, 3])
                st.append(cfg.gap_sigma_m), sr.append(math.radians(cfg.gap_sigma_rot_deg))
        self.ia, self.ib = np.array(ia, int), np.array(ib, int)
        self.Rm_inv = Rotation.from_matrix(np.array(Rm).reshape(-1, 3, 3)).inv() if ia else None
        self.tm = np.array(tm, float).reshape(-1, 3)
        self.st = np.array(st, float)
        self.sr = np.array(sr, float)

        # constant-velocity prior on frames beside a visual gap (triples i-1, i, i+1)
        gap = np.zeros(self.n, bool)
        if self.n >= 3 and cfg.gap_accel_sigma_mps2 > 0:
            brk = comp[1:] != comp[:-1]  # no ok pair between i and i+1
            gap[1:-1] = brk[:-1] | brk[1:]
        self.cv_i = np.flatnonzero(gap)
        dt1 = np.maximum(t[self.cv_i] - t[self.cv_i - 1], 1e-6) if len(self.cv_i) else t[:0]
        dt2 = np.maximum(t[self.cv_i + 1] - t[self.cv_i], 1e-6) if len(self.cv_i) else t[:0]
        self.cv_dt1, self.cv_dt2 = dt1, dt2
        # velocity change over the triple vs σ_a × the time between the two velocity samples
        self.cv_s = max(cfg.gap_accel_sigma_mps2, 1e-9) * 0.5 * (dt1 + dt2)

        # road-normal (tilt) prior per frame, in camera coordinates (pointing up, at the camera):
        # the mount's up axis tipped by the road's grade (mapping.grade; world up seen from a
        # climbing road leans forward), or each pair's own road normal
        n_up = up_axes_in_cam(
            R_vc, np.zeros(self.n) if grade_rad is None else grade_rad, cfg.cross_fall_rad
        )
        for p in ok_pairs if cfg.tilt_prior_axis == "road_normal" else []:
            pl = np.asarray(p.plane, float)
            if np.all(np.isfinite(pl)):
                n_up[pos_of[p.index_a]] = -plane_normal_cam(pl)
        self.n_up = n_up
        self.s_tilt = math.radians(cfg.tilt_sigma_deg)

        # GPS: interpolation indices and eq. 6.1 headings
        if gps is not None:
            self.gk, self.gw = interp_weights(t, gps.t_s)
            self._build_headings()
        # OBD speed at pair mid-times
        self.obd_v = None
        if cfg.use_obd and drive.obd is not None and len(drive.obd.timestamp_s) > 1 and self.n > 1:
            tm_mid = 0.5 * (t[1:] + t[:-1])
            inside = (tm_mid >= drive.obd.timestamp_s[0]) & (tm_mid <= drive.obd.timestamp_s[-1])
            v = np.interp(tm_mid, drive.obd.timestamp_s, drive.obd.speed_mps)
            self.obd_idx = np.flatnonzero(inside)
            self.obd_v = v[self.obd_idx]
        # gauge: without GPS, pin frame 0 (position, heading); without altitude, pin its height
        if gps is None:
            self.pin = [0, 1, 2, 3, 4, 5]
        elif not bool(np.any(gps.has_alt)):
            self.pin = [5]
        else:
            self.pin = []

    def _build_headings(self) -> None:
        g, cfg = self.gps, self.cfg
        hk, hj, hth, hs = [], [], [], []
        for j in range(len(g.t_s) - 1):
            d = g.enu_m[j + 1, :2] - g.enu_m[j, :2]
            L = float(np.linalg.norm(d))
            if L < cfg.heading_min_baseline_m:
                continue
            comp_heading = float(heading_deg_from_displacement(d[0], d[1]))  # eq. 6.1, compass
            tmid = 0.5 * (g.t_s[j] + g.t_s[j + 1])
            k = int(np.argmin(np.abs(self.t - tmid)))
            if abs(self.t[k] - tmid) > 0.5 * (g.t_s[j + 1] - g.t_s[j]):
                continue
            sig = max(
                math.radians(cfg.heading_sigma_deg),
                math.atan(math.sqrt(g.sigma_m[j] ** 2 + g.sigma_m[j + 1] ** 2) / L),
            )
            hk.append(k), hj.append(j), hth.append(math.radians(comp_heading)), hs.append(sig)
        self.hk = np.array(hk, int)
        self.hj = np.array(hj, int)  # each heading's first fix (the second is the next one)
        self.hth = np.array(hth, float)
        self.hs = np.array(hs, float)

    # ---------------------------------------------------------------- residuals
    def _poses(self, x: np.ndarray) -> tuple[Rotation, np.ndarray]:
        X = x.reshape(self.n, 6)
        R = Rotation.from_rotvec(X[:, :3]) * self.R0
        return R, self.p0 + X[:, 3:]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        R, p = self._poses(x)
        out = []
        if len(self.ia):
            Ra, Rb = R[self.ia], R[self.ib]
            Rpred = Rb.inv() * Ra  # cam_b_from_cam_a
            rrot = (self.Rm_inv * Rpred).as_rotvec()
            tpred = Rb.inv().apply(p[self.ia] - p[self.ib])
            vis = np.ones(len(self.ia))
            vis[: self.n_vis] = self.vis_scale
            out.append((rrot / (self.sr * vis)[:, None]).ravel())
            out.append(((tpred - self.tm) / (self.st * vis)[:, None]).ravel())
        # tilt prior: road normal maps to world up
        up_w = R.apply(self.n_up)
        out.append((up_w[:, :2] / self.s_tilt).ravel())
        if self.gps is not None:
            g = self.gps
            u = self.gps_used
            k, w = self.gk[u], self.gw[u]
            k1 = np.minimum(k + 1, self.n - 1)
            pred = (1 - w)[:, None] * p[k] + w[:, None] * p[k1]
            s = g.sigma_m[u] * self.gps_scale
            out.append(((pred[:, :2] - g.enu_m[u, :2]) / s[:, None]).ravel())
            alt = g.has_alt[u]
            out.append(
                (pred[alt, 2] - g.enu_m[u][alt, 2]) / (s[alt] * self.cfg.gps_vertical_sigma_factor)
            )
            if len(self.hk):
                fwd = R[self.hk].apply(self.fwd_cam)
                comp = np.arctan2(fwd[:, 0], fwd[:, 1])
                dh = np.angle(np.exp(1j * (comp - self.hth)))
                # a heading holds only while both its fixes do: one from a rejected fix (6 m
                # off) had rotated a whole RTK drive by 0.47° (RMSE 8.6 -> 35 mm)
                on = u[self.hj] & u[self.hj + 1]
                out.append(np.where(on, dh / self.hs, 0.0))
        if len(self.cv_i):
            i = self.cv_i
            dv = (p[i + 1] - p[i]) / self.cv_dt2[:, None] - (p[i] - p[i - 1]) / self.cv_dt1[:, None]
            out.append((dv / self.cv_s[:, None]).ravel())
        if self.obd_v is not None and len(self.obd_idx):
            i = self.obd_idx
            sp_ = np.linalg.norm(p[i + 1] - p[i], axis=1) / np.maximum(
                self.t[i + 1] - self.t[i], 1e-9
            )
            out.append((sp_ - self.obd_v) / self.cfg.obd_sigma_mps)
        if len(self.pin):
            out.append(x[:6][self.pin] / 1e-3)
        return np.concatenate(out)

    def sparsity(self) -> sp.csr_matrix:
        """Which parameters each residual row depends on (for grouped finite differences)."""
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        r0 = 0

        def add(frames_per_row: list[np.ndarray], nrep: int, blocks: slice) -> None:
            nonlocal r0
            m = len(frames_per_row[0])
            base = np.arange(m) * nrep
            cols_in = np.arange(6)[blocks]
            for rr in range(nrep):
                for fr in frames_per_row:
                    for c in cols_in:
                        rows.append(r0 + base + rr)
                        cols.append(fr * 6 + c)
            r0 += m * nrep

        if len(self.ia):
            add([self.ia, self.ib], 3, slice(0, 3))  # rotation residuals
            add([self.ia, self.ib], 3, slice(0, 6))  # translation residuals
        add([np.arange(self.n)], 2, slice(0, 3))
        if self.gps is not None:
            u = self.gps_used
            k = self.gk[u]
            k1 = np.minimum(k + 1, self.n - 1)
            add([k, k1], 2, slice(3, 6))
            alt = self.gps.has_alt[u]
            if alt.any():
                add([k[alt], k1[alt]], 1, slice(3, 6))
            if len(self.hk):
                add([self.hk], 1, slice(0, 3))
        if len(self.cv_i):
            add([self.cv_i - 1, self.cv_i, self.cv_i + 1], 3, slice(3, 6))
        if self.obd_v is not None and len(self.obd_idx):
            add([self.obd_idx, self.obd_idx + 1], 1, slice(3, 6))
        if len(self.pin):
            add([np.zeros(1, int)], len(self.pin), slice(0, 0))  # rows only
            rows.append(r0 - len(self.pin) + np.arange(len(self.pin)))
            cols.append(np.array(self.pin, int))
        rr = np.concatenate(rows) if rows else np.zeros(0, int)
        cc = np.concatenate(cols) if cols else np.zeros(0, int)
        S = sp.coo_matrix((np.ones(len(rr)), (rr, cc)), shape=(r0, 6 * self.n))
        return (S.tocsr() > 0).astype(np.int8)

    # ---------------------------------------------------------------- solve
    def _lsq(self, x0: np.ndarray, rep: PoseReport) -> np.ndarray:
        """Levenberg-Marquardt with iteratively re-weighted robust loss, sparse normal
        equations and a coloured finite-difference Jacobian (a few residual evaluations)."""
        S = self.sparsity().tocoo()
        r = self.residuals(x0)
        if S.shape[0] != len(r):
            raise RuntimeError(f"pose graph: sparsity rows {S.shape[0]} != residuals {len(r)}")
        colors = _color_columns(S.tocsr())
        loss, c = self.cfg.robust_loss, self.cfg.robust_scale
        x = x0.copy()
        cost = _robust_cost(r, loss, c)
        if not math.isfinite(rep.cost_initial):
            rep.cost_initial = cost
        lam = 1e-3
        h = 1e-6
        for _it in range(self.cfg.max_nfev):
            w = _robust_weights(r, loss, c)
            vals = np.empty(len(S.row))
            for g in range(colors.max() + 1):
                cols = np.flatnonzero(colors == g)
                xp = x.copy()
                xp[cols] += h
                d = (self.residuals(xp) - r) / h
                m = colors[S.col] == g
                vals[m] = d[S.row[m]]
            J = sp.csr_matrix((vals, (S.row, S.col)), shape=S.shape)
            JtW = J.T.multiply(w[None, :]).tocsr()
            A = (JtW @ J).tocsc()
            grad = JtW @ r
            dA = A.diagonal()
            improved = False
            for _ in range(10):
                M = A + sp.diags(lam * np.maximum(dA, 1e-9) + 1e-12)
                dx = -spla.spsolve(M.tocsc(), grad)
                x_new = x + dx
                r_new = self.residuals(x_new)
                cost_new = _robust_cost(r_new, loss, c)
                rep.n_iterations += 1
                if np.isfinite(cost_new) and cost_new <= cost:
                    improved = True
                    break
                lam *= 4.0
            if not improved:
                break
            rel = (cost - cost_new) / max(cost, 1e-12)
            x, r, cost = x_new, r_new, cost_new
            lam = max(lam / 3.0, 1e-9)
            if rel < 1e-9 or np.max(np.abs(dx)) < 1e-9:
                break
        rep.cost_final = cost
        return x

    def solve(self, rep: PoseReport) -> np.ndarray:
        x = np.zeros(6 * self.n)
        x = self._lsq(x, rep)
        if self.gps is not None and len(self.gps.t_s):
            for _ in range(2):
                changed = self._reweight(x, rep)
                if not changed:
                    break
                x = self._lsq(x, rep)
        rep.gps_sigma_scale = self.gps_scale
        rep.visual_sigma_scale = self.vis_scale
        if self.gps is not None:
            rep.n_gps_used = int(self.gps_used.sum())
            bad = np.flatnonzero(~self.gps_used)
            rep.gps_outliers = [
                {"gps_index": int(self.gps.orig_index[j]), "timestamp_s": float(self.gps.t_s[j])}
                for j in bad
            ]
            if len(bad):
                log.warning("poses: rejected %d GPS fix(es) as outliers", len(bad))
        R, p = self._poses(x)
        W = np.tile(np.eye(4), (self.n, 1, 1))
        W[:, :3, :3] = R.as_matrix()
        W[:, :3, 3] = p
        return W

    def _gps_errors_m(self, x: np.ndarray) -> np.ndarray:
        _, p = self._poses(x)
        k, w = self.gk, self.gw
        k1 = np.minimum(k + 1, self.n - 1)
        pred = (1 - w)[:, None] * p[k] + w[:, None] * p[k1]
        return np.linalg.norm(pred[:, :2] - self.gps.enu_m[:, :2], axis=1)

    def _reweight(self, x: np.ndarray, rep: PoseReport) -> bool:
        """Robust σ rescaling (MAD of normalised GPS residuals) and GPS outlier rejection."""
        e = self._gps_errors_m(x) / self.gps.sigma_m  # horizontal error in units of σ
        old_used = self.gps_used.copy()
        old_scale = self.gps_scale
        old_vis = self.vis_scale
        if self.cfg.adapt_sigmas and self.gps_used.sum() >= 8:
            # A 2D error norm with per-axis σ has median RAYLEIGH_MEDIAN σ. Only GPS that is
            # clearly worse than its σ says (> 3×) is loosened. The reverse (an RTK receiver
            # reporting HDOP) is left alone: residuals after the fit are biased low, and
            # tightening GPS would over-weight it against vision (measured: worse drift).
            s = float(np.median(e[self.gps_used]) / RAYLEIGH_MEDIAN)
            if s > 3.0:
                self.gps_scale = float(np.clip(s, 1.0, 20.0))
        thr = self.cfg.gps_outlier_sigmas * self.gps_scale
        self.gps_used = (e <= thr) & (~self.gps_held | (e * self.gps.sigma_m <= HELD_READMIT_M))
        if self.gps_used.sum() < min(2, len(e)):
            self.gps_used = old_used
        return (
            not np.array_equal(old_used, self.gps_used)
            or abs(math.log(max(self.gps_scale, 1e-9) / max(old_scale, 1e-9))) > 0.2
            or abs(math.log(max(self.vis_scale, 1e-9) / max(old_vis, 1e-9))) > 0.2
        )
