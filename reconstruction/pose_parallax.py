"""Pose refinements on every match consistent with the homography seed (the rotation-aware
estimator): plane-plus-parallax maximum likelihood (``pose_model="plane_parallax"``), or the
Sampson refinement with a parallax-ratio model selection (``pose_model="select"``).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from roadsurf.core.camera import normalised_from_px
from roadsurf.reconstruction import geometry as g


def refine_pose_plane_parallax(
    px_a: np.ndarray,
    px_b: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    m0: np.ndarray,
    K: np.ndarray,
    max_iter: int = 10,
    outer: int = 2,
    kappa_z: float = 2.0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Plane-plus-parallax maximum likelihood of the pose, with the road relief as a random
    effect. Returns (R, unit t, κ).

    A match is x_b = π(H x_a) + γ_i û_i + noise, with H = K (R + t mᵀ) K⁻¹ the road-plane
    homography and û_i the direction from π(H x_a) to the epipole K t: the parallax γ_i of a
    point off the plane runs along its epipolar line. Modelling γ_i ~ N(0, κσ² ĝ_i²) (ĝ_i: the
    distance to the epipole, normalised) and the pixel noise as N(0, σ²) in both images, each
    transfer residual has covariance σ² (I + J Jᵀ + κ ĝ² ûûᵀ), J = ∂π(Hx)/∂x. Minimising the
    whitened residuals over R, t, m (8 parameters) is then the generalised least squares of
    the pose. κ = 0 is the gold-standard homography (the plane prior used fully, the most
    precise pose on a flat road): the seed, which is that pose, is returned unchanged.
    κ → ∞ drops the along-line component and leaves the epipolar (Sampson-type) fit of a
    general scene. κ is estimated from the data by the method of moments (along-line against
    across-line residual power), less ``kappa_z`` standard errors so that a flat road's
    sampling scatter does not give away the plane, and re-estimated ``outer`` times. No
    threshold switches between the two models: the relief decides. Levenberg–Marquardt with
    an analytic Jacobian (covariance held at the linearisation point), ``max_iter`` steps
    per κ (the two t columns by forward differences); ~5-15 ms for 2000 matches.
    """
    xa = np.column_stack([normalised_from_px(px_a, K), np.ones(len(px_a))])
    xb = normalised_from_px(px_b, K)
    R, t, m = R0.copy(), t0 / np.linalg.norm(t0), np.asarray(m0, float).copy()

    def state(R: np.ndarray, t: np.ndarray, m: np.ndarray, kappa: float) -> dict:
        """Residual, its whitening (closed-form 2x2 Cholesky) and the pieces of the noise model."""
        Hn = R + np.outer(t, m)
        q = xa @ Hn.T
        w = q[:, 2]
        xp = q[:, :2] / w[:, None]
        r = xb - xp
        # J = ∂π(Hx)/∂(u, v) at x_a, C = I + J Jᵀ (noise of x_a carried into image b)
        j00 = (Hn[0, 0] - xp[:, 0] * Hn[2, 0]) / w
        j01 = (Hn[0, 1] - xp[:, 0] * Hn[2, 1]) / w
        j10 = (Hn[1, 0] - xp[:, 1] * Hn[2, 0]) / w
        j11 = (Hn[1, 1] - xp[:, 1] * Hn[2, 1]) / w
        c11, c12, c22 = 1 + j00**2 + j01**2, j00 * j10 + j01 * j11, 1 + j10**2 + j11**2
        u = t[None, :2] - t[2] * xp  # towards the epipole: the parallax direction
        gl = np.linalg.norm(u, axis=1) + 1e-300
        u = u / gl[:, None]
        g2 = gl**2 / np.mean(gl**2)
        s11 = c11 + kappa * g2 * u[:, 0] ** 2
        s12 = c12 + kappa * g2 * u[:, 0] * u[:, 1]
        s22 = c22 + kappa * g2 * u[:, 1] ** 2
        l11 = np.sqrt(s11)
        l21 = s12 / l11
        l22 = np.sqrt(np.maximum(s22 - l21**2, 1e-300))
        rw1 = r[:, 0] / l11
        rw2 = (r[:, 1] - l21 * rw1) / l22
        return dict(
            q=q, w=w, xp=xp, r=r, u=u, g2=g2, C=(c11, c12, c22), L=(l11, l21, l22),
            cost=float(np.sum(rw1**2) + np.sum(rw2**2)), rw=np.concatenate([rw1, rw2]),
        )  # fmt: skip

    def estimate_kappa(st: dict) -> float:
        u, r = st["u"], st["r"]
        c11, c12, c22 = st["C"]
        par = r[:, 0] * u[:, 0] + r[:, 1] * u[:, 1]
        perp = -r[:, 0] * u[:, 1] + r[:, 1] * u[:, 0]
        c_par = c11 * u[:, 0] ** 2 + 2 * c12 * u[:, 0] * u[:, 1] + c22 * u[:, 1] ** 2
        c_perp = c11 * u[:, 1] ** 2 - 2 * c12 * u[:, 0] * u[:, 1] + c22 * u[:, 0] ** 2
        sigma2 = float(np.mean(perp**2) / np.mean(c_perp)) + 1e-300
        k_i = (par**2 / sigma2 - c_par) / np.mean(st["g2"])  # per-point moment terms
        k_se = float(np.std(k_i) / np.sqrt(len(k_i)))
        return float(np.clip(np.mean(k_i) - kappa_z * k_se, 0.0, 1e8))

    def tangent(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.array([1.0, 0, 0]) if abs(t[0]) < 0.9 else np.array([0, 1.0, 0])
        b1 = np.cross(t, a)
        b1 /= np.linalg.norm(b1)
        return b1, np.cross(t, b1)

    kappa = 0.0
    for _ in range(max(1, outer)):
        kappa = estimate_kappa(state(R, t, m, 0.0))
        if kappa == 0.0:  # the homography model explains the matches (the seed's own model)
            break
        st = state(R, t, m, kappa)
        lam = 1e-3
        for _ in range(max_iter):
            # Jacobian of q = (R + t mᵀ) x over (ω, τ1, τ2, m): ω rotates R on the left,
            # τ moves t in its tangent plane, m is free.
            b1, b2 = tangent(t)
            Rx = xa @ R.T
            mx = xa @ m
            Jq = np.empty((len(xa), 3, 8))
            Jq[:, :, 0] = np.stack([0 * mx, -Rx[:, 2], Rx[:, 1]], 1)  # e_k x (R x)
            Jq[:, :, 1] = np.stack([Rx[:, 2], 0 * mx, -Rx[:, 0]], 1)
            Jq[:, :, 2] = np.stack([-Rx[:, 1], Rx[:, 0], 0 * mx], 1)
            Jq[:, :, 3] = mx[:, None] * b1
            Jq[:, :, 4] = mx[:, None] * b2
            Jq[:, :, 5:8] = t[None, :, None] * xa[:, None, :]
            w, xp = st["w"], st["xp"]
            # r = x_b − π(q): ∂r/∂p = −(Jq[:, k] − π_k Jq[:, 2]) / w
            d1 = -(Jq[:, 0] - xp[:, :1] * Jq[:, 2]) / w[:, None]
            d2 = -(Jq[:, 1] - xp[:, 1:2] * Jq[:, 2]) / w[:, None]
            l11, l21, l22 = st["L"]
            a1 = d1 / l11[:, None]
            a2 = (d2 - l21[:, None] * a1) / l22[:, None]
            A = np.concatenate([a1, a2])
            # t also turns the epipolar lines (û, the split into along/across components):
            # with large κ that is where all of t's information is, so those two columns are
            # differentiated through the whole whitened residual (forward differences).
            for k, b in ((3, b1), (4, b2)):
                t_h = t + 1e-7 * b
                A[:, k] = (state(R, t_h / np.linalg.norm(t_h), m, kappa)["rw"] - st["rw"]) / 1e-7
            JtJ, Jtr = A.T @ A, A.T @ st["rw"]
            improved = False
            # Marquardt damping on the diagonal, floored so that a parameter the data barely
            # constrain (the plane m when κ is huge) cannot make the system singular.
            dg = np.diag(JtJ) + 1e-12 * float(np.max(np.diag(JtJ)))
            while lam < 1e8:
                delta = -np.linalg.solve(JtJ + lam * np.diag(dg), Jtr)
                R_n = g.rotation_from_axis_angle(delta[:3]) @ R
                t_n = t + delta[3] * b1 + delta[4] * b2
                t_n /= np.linalg.norm(t_n)
                m_n = m + delta[5:8]
                st_n = state(R_n, t_n, m_n, kappa)
                if st_n["cost"] < st["cost"]:
                    improved = st["cost"] - st_n["cost"] > 1e-8 * st["cost"]
                    R, t, m, st, lam = R_n, t_n, m_n, st_n, max(lam / 10, 1e-9)
                    break
                lam *= 10
            if not improved:
                break
    return R, t, kappa


def refine_pose_sampson(
    px_a: np.ndarray, px_b: np.ndarray, R0: np.ndarray, t0: np.ndarray, K: np.ndarray, max_nfev: int
) -> tuple[np.ndarray, np.ndarray]:
    """Two-view bundle adjustment reduced to the pose: minimise Sampson errors (first-order
    equal to the reprojection error with optimally triangulated points) over R (axis-angle
    update) and the unit t direction (2-D tangent update)."""
    t0 = t0 / np.linalg.norm(t0)
    a = np.array([1.0, 0, 0]) if abs(t0[0]) < 0.9 else np.array([0, 1.0, 0])
    b1 = np.cross(t0, a)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(t0, b1)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = g.rotation_from_axis_angle(p[:3]) @ R0
        t = t0 + p[3] * b1 + p[4] * b2
        return R, t / np.linalg.norm(t)

    def resid(p: np.ndarray) -> np.ndarray:
        R, t = unpack(p)
        return g.sampson_px(g.fundamental_from_pose(R, t, K), px_a, px_b)

    sol = least_squares(resid, np.zeros(5), method="lm", max_nfev=max_nfev * 6, x_scale=1e-3)
    return unpack(sol.x)


def parallax_ratio(
    px_a: np.ndarray, px_b: np.ndarray, H: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray
) -> float:
    """mean ||x_b − H x_a||² / (4 · mean Sampson²): about 1 when the matches are planar up to
    noise (4 = two noisy images x two axes, against one constrained direction for Sampson)."""
    hx = np.column_stack([px_a, np.ones(len(px_a))]) @ H.T
    r_h = np.sum((px_b - hx[:, :2] / hx[:, 2:3]) ** 2, axis=1)
    s = g.sampson_px(g.fundamental_from_pose(R, t, K), px_a, px_b) ** 2
    return float(np.mean(r_h) / (4.0 * np.mean(s) + 1e-300))
