"""Slanted-window second pass of the dense match (``DenseHeightConfig.slant_sigmas``).

``matching.refine`` fits one parallax s per window: its window is fronto-parallel in parallax.
On a steep defect wall the parallax changes by a sizeable part of a pixel across the window,
and the window's texture weights the fit towards whichever side holds the strongest gradient:
the wall reads blurred towards its rim. Here each pixel's window is slanted by the local
parallax gradient a = (∂s/∂u, ∂s/∂v) of the first pass (a plane fitted to the valid
parallaxes of a (win + 4)² neighbourhood), as in PatchMatch stereo's slanted support windows
(Bleyer et al. 2011) or an affine Lucas-Kanade with its slope held: the window's pixel x + δ
is sampled at s + a·δ along its epipolar direction, and s is refined by 1D Lucas-Kanade with
a local gain and offset (``matching.refine``'s model, one window per pixel).

Only where the gradient is significant against its own noise (the Wald statistic
aᵀ S a / σ² of the plane fit at least ``slant_sigmas``², S the fit's design moments, σ² its
residual variance) and large enough to matter (``MIN_SPAN_PX`` across the window, and half the
window's change above the first match's σ): the flat road (a = 0 by construction of the
plane-warped pair) keeps its first-pass match. A slanted match replaces the first one where
its ZNCC is at least as high and it converged.

Measured: a synthetic wall (the parallax rising 0.4-0.8 px/px across 20 px) 0.17-0.34 ->
0.03 px RMS (tests/reconstruction/test_dense_slanted.py); the seed-7 45° stereo pair
(benchmarks/stereo_pair.py), per pixel against a ray cast of the 1 mm truth, pothole RMS
3.97 -> 3.87 mm (9 % of the work grid's pixels matched again). The walls' larger errors there
come from elsewhere: the pixels filled from the coarser grid (``pyramid``: 10 % of the
pothole's pixels, RMS 7.7 mm) and the cell fixed point of the surface
(``mapping.dense_cells``).

The same torch code on CPU and CUDA; windows are gathered for the selected pixels only.
"""

from __future__ import annotations

import dataclasses
import logging

import torch
import torch.nn.functional as F

from roadsurf.reconstruction.dense.checks import STEP_MAX_PX
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.matching import (
    INSIDE_MIN,
    RefineResult,
    box,
    gradients,
)

log = logging.getLogger(__name__)

FIT_MARGIN_PX = 2  # the gradient's fit spans the window plus this on each side (px)
MIN_FIT_SHARE = 0.5  # a fit needs at least this share of its neighbourhood valid (−)
# smallest parallax change across the window that is matched again (px): its edge samples then
# sit 0.25 px off a fronto-parallel window's parallax, 5 x the Lucas-Kanade's convergence
# tolerance (checks.STEP_MAX_PX). The road's own millimetre relief reaches 0.2 px across a
# window at 0.5 m (seed-7 45° pair: 0.2 px selected 38 % of the pixels, 0.5 px 9 %, for the
# same gain; a plane a little off adds ~1 px across the whole image, far below)
MIN_SPAN_PX = 0.5
# Lucas-Kanade steps of the slanted pass (count): it starts from the first pass's converged
# parallax, whose error on a wall is a fraction of a pixel
SLANT_ITERS = 3


def window_offsets(side: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(1, side²) δu, δv of a side x side window's pixels from its centre (px)."""
    r = side // 2
    d = torch.arange(-r, r + 1, device=device, dtype=torch.float32)
    dv, du = torch.meshgrid(d, d, indexing="ij")
    return du.reshape(1, -1), dv.reshape(1, -1)


def gather_windows(
    field: torch.Tensor, idx: torch.Tensor, side: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """field (1, 1, H, W) at the side x side windows of the pixels idx (N,) (flat indices):
    (N, side²) values (clamped at the border), flat indices and a bool mask of the samples
    inside the grid."""
    H, W = field.shape[-2:]
    du, dv = window_offsets(side, field.device)
    yq = (idx // W)[:, None] + dv.long()
    xq = (idx % W)[:, None] + du.long()
    inside = (xq >= 0) & (xq < W) & (yq >= 0) & (yq < H)
    qi = yq.clamp(0, H - 1) * W + xq.clamp(0, W - 1)
    return field.reshape(-1)[qi], qi, inside


def parallax_gradient(
    shift: torch.Tensor, valid: torch.Tensor, side: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Least-squares plane s ≈ s0 + a_u u + a_v v over the valid pixels of each side x side
    neighbourhood. shift (1, 1, H, W) px, valid (1, 1, H, W) bool. Returns a_u, a_v (px/px)
    and the Wald statistic z² = aᵀ S a / σ² (−; 0 where fewer than ``MIN_FIT_SHARE`` of the
    neighbourhood is valid), all (1, 1, H, W). Centred moments are translation-invariant, so
    they come from window means (``matching.box``) of the coordinates from the grid's centre
    and of the parallax minus its median: small numbers, float32 is enough."""
    au, av, z2, _ = plane_fit(shift, valid, side)
    return au, av, z2


def plane_fit(
    shift: torch.Tensor, valid: torch.Tensor, side: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``parallax_gradient``'s a_u, a_v and z², and the RMS residual of the plane over the
    neighbourhood's valid pixels (px; 0 where there is no fit), all (1, 1, H, W)."""
    dev, dt = shift.device, shift.dtype
    H, W = shift.shape[-2:]
    v, u = torch.meshgrid(
        torch.arange(H, device=dev, dtype=dt) - 0.5 * (H - 1),
        torch.arange(W, device=dev, dtype=dt) - 0.5 * (W - 1),
        indexing="ij",
    )
    u, v = u[None, None], v[None, None]
    m = valid.to(dt)
    ref = shift[valid].median() if bool(valid.any()) else torch.zeros((), device=dev, dtype=dt)
    s = torch.where(valid, shift - ref, torch.zeros((), device=dev, dtype=dt))
    ms = m * s
    e = box(torch.cat([m, m * u, m * v, m * u * u, m * v * v, m * u * v, ms, ms * u, ms * v,
                       ms * s], 1), side)  # fmt: skip
    share = e[:, :1]
    e = e[:, 1:] / share.clamp_min(1e-6)  # means over the valid pixels
    eu, ev, euu, evv, euv, es, esu, esv, ess = e.unbind(1)
    cuu, cvv, cuv = euu - eu * eu, evv - ev * ev, euv - eu * ev
    cus, cvs, css = esu - eu * es, esv - ev * es, ess - es * es
    n = share[:, 0] * (side * side)  # the grid's border (no walls there) counted whole
    det = cuu * cvv - cuv * cuv
    ok = (n >= MIN_FIT_SHARE * side * side) & (det > 1e-3)
    det = torch.where(ok, det, torch.ones_like(det))
    au = (cvv * cus - cuv * cvs) / det
    av = (cuu * cvs - cuv * cus) / det
    explained = au * cus + av * cvs  # aᵀ S a / n
    sigma2 = ((css - explained).clamp_min(0.0) * n / (n - 3.0).clamp_min(1.0)).clamp_min(1e-8)
    z2 = torch.where(ok, explained * n / sigma2, torch.zeros_like(explained))
    zero = torch.zeros_like(au)
    rms = torch.where(ok, (css - explained).clamp_min(0.0).sqrt(), zero)
    return (
        torch.where(ok, au, zero)[:, None],
        torch.where(ok, av, zero)[:, None],
        z2[:, None],
        rms[:, None],
    )


def window_lk(
    R: torch.Tensor,
    ref_in: torch.Tensor,
    xq: torch.Tensor,
    yq: torch.Tensor,
    wq: tuple[torch.Tensor, torch.Tensor],
    slope: torch.Tensor | None,
    stack: torch.Tensor,
    s0: torch.Tensor,
    iters: int,
    cfg: DenseHeightConfig,
) -> tuple[torch.Tensor, ...]:
    """One parallax per window by Lucas-Kanade along ŵ with a local gain and offset
    (``matching.refine``'s model), shared by the slanted and the shifted passes. R, ref_in (N,
    K): the reference window's samples and where they count; xq, yq (N, K) px: their positions;
    wq (N, K) each: ŵ there; ``slope`` (N, K) px: the window's parallax plane relative to its
    centre (None: fronto-parallel); ``stack`` (1, 3, H, W): target, its gradient along ŵ, its
    inside mask; s0 (N,) px: the start. Returns (s, var, ncc, grad, last, n, w): parallax,
    its variance (px²), ZNCC, RMS target gradient (DN/px), last step (px), samples counted and
    their weights (N, K)."""
    H, W = stack.shape[-2:]
    dt = R.dtype
    wq_x, wq_y = wq

    def window_stats(sv: torch.Tensor) -> tuple[torch.Tensor, ...]:
        sq = sv[:, None] if slope is None else sv[:, None] + slope
        px, py = xq + sq * wq_x, yq + sq * wq_y
        grid = torch.stack([px * (2.0 / (W - 1)) - 1.0, py * (2.0 / (H - 1)) - 1.0], -1)
        smp = F.grid_sample(stack, grid[None], mode="bilinear", align_corners=True)[0]
        J, G = smp[0], smp[1]
        w = (ref_in & (smp[2] >= INSIDE_MIN)).to(dt)
        n = w.sum(1).clamp_min(1.0)

        def mean(x: torch.Tensor) -> torch.Tensor:
            return (w * x).sum(1) / n

        mu_r, mu_j, mu_g = mean(R), mean(J), mean(G)
        Rt, Jt, Gt = R - mu_r[:, None], J - mu_j[:, None], G - mu_g[:, None]
        var_r = mean(Rt * Rt).clamp_min(0)
        var_j = mean(Jt * Jt).clamp_min(1e-6)
        var_g = mean(Gt * Gt).clamp_min(1e-9)
        return Rt, Jt, Gt, w, n, var_r, var_j, var_g

    s = s0.clone()
    last = torch.full_like(s, float("inf"))
    for it in range(iters + 1):
        Rt, Jt, Gt, w, n, var_r, var_j, var_g = window_stats(s)
        g = (var_r / var_j).sqrt().clamp(0.5, 2.0)
        if it == iters:
            break
        res = Rt - g[:, None] * Jt
        step = ((w * Gt * res).sum(1) / n) / (g * var_g)
        step = step.clamp(-1.0, 1.0)
        last = step.abs()
        s = s + step
    cov_rj = (w * Rt * Jt).sum(1) / n
    ncc = cov_rj / (var_r.sqrt() * var_j.sqrt() + 1e-3)
    resid = (2.0 * var_r * (1.0 - ncc)).clamp_min(2.0 * cfg.noise_dn * cfg.noise_dn)
    var = resid / (n * g * g * var_g)
    return s, var, ncc, var_g.sqrt(), last, n, w


def slanted_refine(
    ref: torch.Tensor,
    tgt: torch.Tensor,
    tgt_mask: torch.Tensor,
    ref_mask: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
    first: RefineResult,
    valid: torch.Tensor,
    win: int,
    cfg: DenseHeightConfig,
) -> tuple[RefineResult, torch.Tensor]:
    """The slanted second pass (module docstring) of the forward match ``first``. ``valid``
    (1, 1, H, W) bool: the first pass's accepted pixels; those whose parallax gradient is
    significant (``cfg.slant_sigmas``) are matched again in windows slanted by it
    (``SLANT_ITERS`` Lucas-Kanade steps from the first parallax) and take the slanted match where it converged,
    its window lies inside both images and its ZNCC is at least the first one's. Returns
    ``first`` with those pixels' shift, variance, ZNCC, texture and last step replaced, and
    the (1, 1, H, W) bool mask of the replaced pixels. Images and fields as in
    ``matching.refine``."""
    H, W = ref.shape[-2:]
    dev, dt = ref.device, ref.dtype
    au, av, z2 = parallax_gradient(first.shift, valid, win + 2 * FIT_MARGIN_PX)
    # significant against the fit's noise, and large enough to matter: across the window the
    # parallax spans at least MIN_SPAN_PX and half the window's change exceeds the first
    # match's σ (the first pass's neighbouring parallaxes are correlated through their shared
    # windows, so the Wald test alone calls the flat road's tiny gradients significant)
    grad = (au * au + av * av).sqrt()
    cand = valid & (z2 >= cfg.slant_sigmas**2) & (grad * (win - 1) >= MIN_SPAN_PX)
    cand &= grad * (win // 2) >= first.var.sqrt()
    idx = torch.nonzero(cand[0, 0].reshape(-1)).squeeze(1)
    none = torch.zeros_like(valid)
    if idx.numel() == 0:
        return first, none
    au, av = au.reshape(-1)[idx], av.reshape(-1)[idx]
    du, dv = window_offsets(win, dev)
    R, qi, inside = gather_windows(ref, idx, win)
    xq = (idx % W).to(dt)[:, None] + du
    yq = (idx // W).to(dt)[:, None] + dv
    wq_x, wq_y = wx.reshape(-1)[qi], wy.reshape(-1)[qi]
    ref_in = inside & (ref_mask.reshape(-1)[qi] >= INSIDE_MIN)
    slope = au[:, None] * du + av[:, None] * dv  # (N, K) px
    # the target's gradient along ŵ on its own grid, as ``matching.refine`` takes it (ŵ turns
    # by well under 1 % between a pixel and its match)
    gx, gy = gradients(tgt)
    stack = torch.cat([tgt, gx * wx + gy * wy, tgt_mask.to(dt)], 1)
    s, var, ncc, grad_w, last, n, w = window_lk(
        R, ref_in, xq, yq, (wq_x, wq_y), slope, stack, first.shift.reshape(-1)[idx], SLANT_ITERS,
        cfg,
    )  # fmt: skip
    tol = (cfg.step_max_sigma * var.sqrt()).clamp_min(STEP_MAX_PX)
    full = n >= w.shape[1] * INSIDE_MIN - 0.5  # the slanted window wholly inside both images
    better = (ncc >= first.ncc.reshape(-1)[idx]) & (last <= tol) & full
    better &= torch.isfinite(s) & torch.isfinite(var)
    idx = idx[better]

    def put(field: torch.Tensor, val: torch.Tensor) -> torch.Tensor:
        out = field.clone().reshape(-1)
        out[idx] = val[better].to(out.dtype)
        return out.reshape(field.shape)

    new = dataclasses.replace(
        first,
        shift=put(first.shift, s),
        var=put(first.var, var),
        ncc=put(first.ncc, ncc),
        grad=put(first.grad, grad_w),
        last_step=put(first.last_step, last),
    )
    log.debug("dense: slanted pass on %d px, %d replaced", int(better.numel()), int(idx.numel()))
    mask = none.clone().reshape(-1)
    mask[idx] = True
    return new, mask.reshape(valid.shape)
