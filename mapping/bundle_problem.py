"""One window of the bundle adjustment (issue 30) as a sparse least-squares problem.

Unknowns: the free frames' poses (rotation vector φ with R = Exp(φ) R0, camera centre C), each
window frame's road plane in its camera (Z = p0 X + p1 Y + p2), every track point (world) and
the GPS - camera time offset τ. Residuals, each whitened by its σ so that one robust loss fits
all: reprojection (px), point-on-plane (road relief; a frame's points share one plane's
weight), camera height above its plane (metric scale), GPS position at the fix time minus τ
(interpolated between the frames around it), a weak pull towards the pose graph's centres (gauge
without GPS), the tilt prior, the pairs' relative motions (the pose graph's factors), constant
motion across frames no track ties, OBD speed and a prior on τ. Optionally the focal length
(log scale ψ) and a radial distortion correction κ (k1's error: the observations are pixels
undistorted with camera.yaml's k1, so they sit at x (1 + κ r²) of the true ideal ones, r the
normalised radius; first order in κ times camera.yaml's own distortion), each with a prior; the
pairs' translations, solved with camera.yaml's focal, follow the focal scale
(``pair_translation``). With a rolling shutter each observation is projected from its row's pose
(``row_offset``). The Jacobian is analytic (small-angle rotation derivatives; the solver
re-linearises every step)."""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from roadsurf.mapping.bundle_terms import (
    ObsTerms,
    WindowData,
    observation_terms,
    pair_translation,
)

# σ of the change of the window's mean camera tilt from the pose graph's with a rolling shutter
# (deg): a roll of every camera about a straight track, the points turning with them, is a gauge
# (GPS and the images do not see it), so the bundle keeps the pose graph's; 0.1° moves the map
# 2 mm sideways at 1.1 m. The per-frame tilt prior (σ_tilt) keeps each frame's own tilt free
TILT_MEAN_SIGMA_DEG = 0.1


def _skew_cross(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.cross(a, v)


class WindowProblem:
    def __init__(self, d: WindowData) -> None:
        self.d = d
        F, P = len(d.t), len(d.X0)
        self.F, self.P = F, P
        free_idx = np.flatnonzero(d.free)
        self.pose_col = np.full(F, -1, int)
        self.pose_col[free_idx] = 6 * np.arange(len(free_idx))
        self.plane_col0 = 6 * len(free_idx)
        # column order: poses, planes, τ (the camera side), then the points
        nxt = self.plane_col0 + 3 * F
        self.tau_col = nxt if d.sigma_tau_s > 0 else -1
        nxt += 1 if d.sigma_tau_s > 0 else 0
        self.focal_col = nxt if d.sigma_focal > 0 else -1
        nxt += 1 if d.sigma_focal > 0 else 0
        self.k1_col = nxt if d.sigma_k1 > 0 else -1
        self.point_col0 = nxt + (1 if d.sigma_k1 > 0 else 0)
        self.n = self.point_col0 + 3 * P
        self.gps_used = np.ones(len(d.gps_t), bool)
        self.gps_scale = 1.0
        # the relief term's weight per observation: a frame's road points depart from its plane
        # together (undulation, grade change and ruts are smooth over a frame's footprint), so
        # their N residuals carry about one plane's worth of information, not N: each weighs
        # 1/√N of its frame's (without this the planes bent the point cloud and, through it,
        # the cameras' tilt: potholes, 5-frame rotation error 0.15° against the pose graph's
        # 0.04°)
        road = np.ones(len(d.obs_p)) if d.on_road is None else d.on_road[d.obs_p].astype(float)
        n_road = np.bincount(d.obs_f, weights=road, minlength=F)
        self.relief_w = road / np.sqrt(np.maximum(n_road[d.obs_f], 1.0))
        self._cache: tuple[bytes, np.ndarray, sp.csr_matrix] | None = None

    # ---------------------------------------------------------------- state
    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        d = self.d
        R, C = d.R0.copy(), d.C0.copy()
        fr = np.flatnonzero(self.pose_col >= 0)
        if len(fr):
            X = x[: self.plane_col0].reshape(-1, 6)
            R[fr] = (Rotation.from_rotvec(X[:, :3]) * Rotation.from_matrix(d.R0[fr])).as_matrix()
            C[fr] = d.C0[fr] + X[:, 3:]
        planes = d.planes0 + x[self.plane_col0 : self.plane_col0 + 3 * self.F].reshape(-1, 3)
        pts = d.X0 + x[self.point_col0 :].reshape(-1, 3)
        tau = d.tau0 + (x[self.tau_col] if self.tau_col >= 0 else 0.0)
        return R, C, planes, pts, float(tau)

    def focal_log_scale(self, x: np.ndarray) -> float:
        """ψ: the focal length is the calibration's times exp(ψ)."""
        return self.d.focal0 + (float(x[self.focal_col]) if self.focal_col >= 0 else 0.0)

    def k1_correction(self, x: np.ndarray) -> float:
        """κ: the true k1 minus camera.yaml's (first order)."""
        return self.d.k1_0 + (float(x[self.k1_col]) if self.k1_col >= 0 else 0.0)

    def fun(self, x: np.ndarray) -> np.ndarray:
        return self._eval(x)[0]

    def jac(self, x: np.ndarray) -> sp.csr_matrix:
        return self._eval(x)[1]

    def _eval(self, x: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        key = x.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        r, J = self._build(x)
        self._cache = (key, r, J)
        return r, J

    # ---------------------------------------------------------------- residuals + Jacobian
    def _obs_terms(
        self, x: np.ndarray, R: np.ndarray, C: np.ndarray, planes: np.ndarray, pts: np.ndarray
    ) -> ObsTerms:
        fs = float(np.exp(self.focal_log_scale(x)))
        return observation_terms(
            self.d, self.relief_w, R, C, planes, pts, fs, self.k1_correction(x)
        )

    def point_terms(self, x: np.ndarray) -> ObsTerms:
        """The observations' residuals and point derivatives alone (the points' own steps)."""
        R, C, planes, pts, _ = self.unpack(x)
        return self._obs_terms(x, R, C, planes, pts)

    def _build(self, x: np.ndarray, points: bool = True) -> tuple[np.ndarray, sp.csr_matrix]:
        """Residuals and the sparse Jacobian; points=False: without the point columns (their
        entries are ``point_terms``' dense blocks), the matrix (rows x point_col0)."""
        d = self.d
        R, C, planes, pts, tau = self.unpack(x)
        res: list[np.ndarray] = []
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        r0 = 0

        def put(row: np.ndarray, col: np.ndarray, val: np.ndarray) -> None:
            ok = col >= 0
            rows.append(row[ok])
            cols.append(col[ok])
            vals.append(val[ok])

        def put_block(row: np.ndarray, col0: np.ndarray, g: np.ndarray) -> None:
            """row (m,), first column (m,) of a 3-wide block, gradient (m, 3)."""
            for k in range(3):
                put(row, np.where(col0 >= 0, col0 + k, -1), g[:, k])

        # ------------------------------------------------ reprojection and point-on-plane
        f, p = d.obs_f, d.obs_p
        m = len(f)
        if m:
            ot = self._obs_terms(x, R, C, planes, pts)
            res += list(ot.res)
            s = d.sigma_px
            pose0 = self.pose_col[f]
            pcol = self.point_col0 + 3 * p
            for k in range(3):
                row = r0 + k * m + np.arange(m)
                if points:
                    put_block(row, pcol, ot.Ax[k])
                put_block(row, np.where(pose0 >= 0, pose0 + 3, -1), -ot.Ax[k])
                put_block(row, pose0, _skew_cross(ot.A[k], ot.v))
            if self.focal_col >= 0:  # du/dψ = u - cx
                fc = np.full(m, self.focal_col)
                put(r0 + np.arange(m), fc, (ot.u - d.K[0, 2]) / s)
                put(r0 + m + np.arange(m), fc, (ot.w - d.K[1, 2]) / s)
            if self.k1_col >= 0:  # du/dκ = fx xn r²
                kc = np.full(m, self.k1_col)
                put(r0 + np.arange(m), kc, ot.fx * ot.xn * ot.r2 / s)
                put(r0 + m + np.arange(m), kc, ot.fy * ot.yn * ot.r2 / s)
            row = r0 + 2 * m + np.arange(m)
            put_block(row, self.plane_col0 + 3 * f, ot.gpl)
            r0 += 3 * m

        # ------------------------------------------------ camera height above its plane
        sn = np.sqrt(1.0 + planes[:, 0] ** 2 + planes[:, 1] ** 2)
        res.append((planes[:, 2] / sn - d.height_m) / d.sigma_height_m)
        gh = np.column_stack(
            [
                -planes[:, 2] * planes[:, 0] / sn**3,
                -planes[:, 2] * planes[:, 1] / sn**3,
                1.0 / sn,
            ]
        )
        put_block(
            r0 + np.arange(self.F), self.plane_col0 + 3 * np.arange(self.F), gh / d.sigma_height_m
        )
        r0 += self.F

        # ------------------------------------------------ GPS at fix time minus τ
        gi = np.flatnonzero(self.gps_used)
        if len(gi):
            tq = d.gps_t[gi] - tau
            kg = np.clip(np.searchsorted(d.t, tq, side="right") - 1, 0, self.F - 2)
            dt = np.maximum(d.t[kg + 1] - d.t[kg], 1e-9)
            wgt = (tq - d.t[kg]) / dt
            pred = (1 - wgt)[:, None] * C[kg] + wgt[:, None] * C[kg + 1]
            vel = (C[kg + 1] - C[kg]) / dt[:, None]
            sg = d.gps_sigma[gi] * self.gps_scale
            alt = d.gps_has_alt[gi]
            for ax in range(3):
                sel = np.arange(len(gi)) if ax < 2 else np.flatnonzero(alt)
                if not len(sel):
                    continue
                sig = sg[sel] * (1.0 if ax < 2 else d.vertical_factor)
                res.append((pred[sel, ax] - d.gps_enu[gi[sel], ax]) / sig)
                row = r0 + np.arange(len(sel))
                for kk, ww in ((kg[sel], 1 - wgt[sel]), (kg[sel] + 1, wgt[sel])):
                    c = self.pose_col[kk]
                    put(row, np.where(c >= 0, c + 3 + ax, -1), ww / sig)
                if self.tau_col >= 0:
                    put(row, np.full(len(sel), self.tau_col), -vel[sel, ax] / sig)
                r0 += len(sel)

        # ------------------------------------------------ pull towards the pose graph, tilt
        fr = np.flatnonzero(self.pose_col >= 0)
        if len(fr):
            res.append(((C[fr] - d.C_prior[fr]) / d.sigma_prior_m).ravel())
            for ax in range(3):
                put(
                    r0 + 3 * np.arange(len(fr)) + ax,
                    self.pose_col[fr] + 3 + ax,
                    np.full(len(fr), 1.0 / d.sigma_prior_m),
                )
            r0 += 3 * len(fr)
            up = np.einsum("mij,mj->mi", R[fr], d.n_up[fr])
            res.append((up[:, :2] / d.sigma_tilt_rad).ravel())
            # d(up)/dφ = -[up]x
            zf = np.zeros(len(fr))
            rows_g = (
                np.column_stack([zf, up[:, 2], -up[:, 1]]),
                np.column_stack([-up[:, 2], zf, up[:, 0]]),
            )
            for ax in range(2):
                put_block(
                    r0 + 2 * np.arange(len(fr)) + ax,
                    self.pose_col[fr],
                    rows_g[ax] / d.sigma_tilt_rad,
                )
            r0 += 2 * len(fr)
            if d.obs_time_s is not None:
                # a rolling shutter: the window's mean tilt stays the pose graph's (a gauge the
                # per-frame prior holds only to σ_tilt/√F: the row-pose terms tipped it by 1.0°,
                # the map 19 mm sideways, for 0.0002 px less reprojection RMS; 30 fps, 20 ms
                # readout, 24 frames)
                sc = math.radians(TILT_MEAN_SIGMA_DEG)
                up0 = np.einsum("mij,mj->mi", d.R0[fr], d.n_up[fr])
                res.append((up[:, :2].mean(0) - up0[:, :2].mean(0)) / sc)
                for ax in range(2):
                    put_block(
                        np.full(len(fr), r0 + ax), self.pose_col[fr], rows_g[ax] / (sc * len(fr))
                    )
                r0 += 2

        # ------------------------------------------------ constant motion across untied frames
        if len(d.gap_i):
            a, b = d.gap_i, d.gap_i + 1
            Rm = np.einsum("mji,mjk->mik", d.R0[b], d.R0[a])
            tm = np.einsum("mji,mj->mi", d.R0[b], d.C0[a] - d.C0[b])
            Rp = np.einsum("mji,mjk->mik", R[b], R[a])
            rrot = (Rotation.from_matrix(Rm).inv() * Rotation.from_matrix(Rp)).as_rotvec()
            vab = C[a] - C[b]
            tp = np.einsum("mji,mj->mi", R[b], vab)
            res.append((rrot / d.sigma_gap_rad).ravel())
            res.append(((tp - tm) / d.sigma_gap_m).ravel())
            nb = len(a)
            for ax in range(3):
                row = r0 + 3 * np.arange(nb) + ax
                Ra_t = R[a][:, :, ax] / d.sigma_gap_rad  # row ax of R_a^T
                put_block(row, self.pose_col[a], Ra_t)
                put_block(row, self.pose_col[b], -Ra_t)
            r0 += 3 * nb
            for ax in range(3):
                row = r0 + 3 * np.arange(nb) + ax
                Rb_t = R[b][:, :, ax] / d.sigma_gap_m
                ca, cb = self.pose_col[a], self.pose_col[b]
                put_block(row, np.where(ca >= 0, ca + 3, -1), Rb_t)
                put_block(row, np.where(cb >= 0, cb + 3, -1), -Rb_t)
                put_block(row, cb, _skew_cross(Rb_t, vab))
            r0 += 3 * nb

        # ------------------------------------------------ the pairs' relative motions
        if d.rel_i is not None and len(d.rel_i) and d.rel_R is not None:
            a, b = d.rel_i, d.rel_i + 1
            Rp = np.einsum("mji,mjk->mik", R[b], R[a])
            rrot = (Rotation.from_matrix(d.rel_R).inv() * Rotation.from_matrix(Rp)).as_rotvec()
            res.append((rrot / d.sigma_rel_rad).ravel())
            for ax in range(3):
                row = r0 + 3 * np.arange(len(a)) + ax
                Ra_t = R[a][:, :, ax] / d.sigma_rel_rad  # row ax of R_a^T
                put_block(row, self.pose_col[a], Ra_t)
                put_block(row, self.pose_col[b], -Ra_t)
            r0 += 3 * len(a)
            if d.rel_t is not None and d.sigma_rel_m is not None:
                vab = C[a] - C[b]
                tp = np.einsum("mji,mj->mi", R[b], vab)
                sg = d.sigma_rel_m[:, None]
                rel_t, drel_t = d.rel_t, None
                psi = self.focal_log_scale(x)
                if d.rel_n is not None and (psi != 0.0 or self.focal_col >= 0):
                    rel_t, drel_t = pair_translation(d.rel_t, d.rel_n, psi)
                res.append(((tp - rel_t) / sg).ravel())
                if drel_t is not None and self.focal_col >= 0:
                    put(
                        r0 + np.arange(3 * len(a)),
                        np.full(3 * len(a), self.focal_col),
                        (-drel_t / sg).ravel(),
                    )
                for ax in range(3):
                    row = r0 + 3 * np.arange(len(a)) + ax
                    Rb_t = R[b][:, :, ax] / sg
                    ca, cb = self.pose_col[a], self.pose_col[b]
                    put_block(row, np.where(ca >= 0, ca + 3, -1), Rb_t)
                    put_block(row, np.where(cb >= 0, cb + 3, -1), -Rb_t)
                    put_block(row, cb, _skew_cross(Rb_t, vab))
                r0 += 3 * len(a)

        # ------------------------------------------------ OBD speed
        if len(d.obd_i):
            a, b = d.obd_i, d.obd_i + 1
            dv = C[b] - C[a]
            L = np.maximum(np.linalg.norm(dv, axis=1), 1e-9)
            dt = np.maximum(d.t[b] - d.t[a], 1e-9)
            res.append((L / dt - d.obd_v) / d.sigma_obd_mps)
            g = dv / (L * dt * d.sigma_obd_mps)[:, None]
            row = r0 + np.arange(len(a))
            ca, cb = self.pose_col[a], self.pose_col[b]
            put_block(row, np.where(cb >= 0, cb + 3, -1), g)
            put_block(row, np.where(ca >= 0, ca + 3, -1), -g)
            r0 += len(a)

        # ------------------------------------------------ prior on τ
        if self.tau_col >= 0:
            res.append(np.array([(tau - d.tau0) / d.sigma_tau_s]))
            put(np.array([r0]), np.array([self.tau_col]), np.array([1.0 / d.sigma_tau_s]))
            r0 += 1

        # ------------------------------------------------ prior on the focal length
        if self.focal_col >= 0:
            res.append(np.array([(self.focal_log_scale(x) - d.focal0) / d.sigma_focal]))
            put(np.array([r0]), np.array([self.focal_col]), np.array([1.0 / d.sigma_focal]))
            r0 += 1

        # ------------------------------------------------ prior on the k1 correction
        if self.k1_col >= 0:
            res.append(np.array([(self.k1_correction(x) - d.k1_0) / d.sigma_k1]))
            put(np.array([r0]), np.array([self.k1_col]), np.array([1.0 / d.sigma_k1]))
            r0 += 1

        r = np.concatenate(res)
        if len(r) != r0:
            raise RuntimeError(f"bundle: {len(r)} residuals but {r0} Jacobian rows")
        J = sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(r0, self.n if points else self.point_col0),
        )
        return r, J

    def gps_errors(self, x: np.ndarray) -> np.ndarray:
        """Horizontal GPS error of every fix in units of its σ (all fixes, used or not)."""
        d = self.d
        _, C, _, _, tau = self.unpack(x)
        tq = d.gps_t - tau
        k = np.clip(np.searchsorted(d.t, tq, side="right") - 1, 0, self.F - 2)
        wgt = (tq - d.t[k]) / np.maximum(d.t[k + 1] - d.t[k], 1e-9)
        pred = (1 - wgt)[:, None] * C[k] + wgt[:, None] * C[k + 1]
        return np.linalg.norm(pred[:, :2] - d.gps_enu[:, :2], axis=1) / (
            d.gps_sigma * self.gps_scale
        )
