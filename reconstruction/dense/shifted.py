"""Shifted-window pass of the dense match (``DenseHeightConfig.shifted_windows``).

A window centred on a pixel next to a depth step (a pothole's rim seen in front of its floor, a
ridge of a rough floor) holds both surfaces; Lucas-Kanade then reads a mix, weighted towards the
side with the stronger texture ("fattening"). Shiftable windows (Bobick & Intille 1999; Fusiello
et al. 1997, "multiple windows") match each such pixel in the windows that hold it at their
edge midpoints and corners, and keep the one on the pixel's own side of the step.

The window with the pixel at offset -δ from its centre is the first pass's window of the pixel
x + δ (δ in {-r, 0, r}² less 0, r = win // 2), and its match that pixel's parallax. Which
window: the one whose parallax the pixel's own 3 x 3 neighbourhood correlates best with (the
window ZNCC alone would pick, next to a rim, the window on the rim's texture that holds the
pixel in a corner), among the accepted ones. That window is then matched on its own, one
parallax for the window, by ``SHIFT_ITERS`` Lucas-Kanade steps with a local gain and offset
(``matching.refine``'s model) from its centre's parallax; it must be wholly inside both images,
textured (``min_grad_dn``), converged and correlate at ``min_ncc``, and it replaces the first
match where the pixel's 3 x 3 neighbourhood correlates better at it than at the first parallax.
The slanted pass (``slanted``) runs afterwards: a wall's pixels are matched again in windows
slanted by their gradient.

Pixels concerned: accepted pixels within a window of one the left-right check refused (the band
a rim hides from one view) or whose window's accepted parallaxes span ``STEP_SPAN_PX`` or more;
the flat road keeps its match. A step so sharpened shows as parallaxes no plane describes,
which ``DenseHeightConfig.step_plane_px`` then refuses at the step itself, where neither side's
window holds the pixel's 3 x 3 neighbourhood (a synthetic 3 px step, tests: the pixels within
a window of it 0.47 -> 0.04 px RMS, the two at the step 1.2-1.9 px off before and after).

Refused pixels are not matched this way: on the seed-7 45° stereo pair (``benchmarks.
dense_pair_truth``) the refused pixels a shifted window would accept, with a left-right check
of its own, read the pothole 8 mm RMS off per pixel, as the coarse-grid fallback does there.

The same torch code on CPU and CUDA; the 3 x 3 neighbourhoods are gathered for the selected
pixels only.
"""

from __future__ import annotations

import dataclasses
import logging

import torch
import torch.nn.functional as F

from roadsurf.reconstruction.dense.checks import REJECT_LR, STEP_MAX_PX
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.matching import (
    INSIDE_MIN,
    RefineResult,
    gradients,
    window_max,
    window_min,
)
from roadsurf.reconstruction.dense.slanted import (
    MIN_SPAN_PX,
    gather_windows,
    window_lk,
    window_offsets,
)

log = logging.getLogger(__name__)

# refusals next to which a pixel's window may straddle a step: the left-right check's (an
# occlusion, the band a rim hides from one view); scattered ZNCC or texture refusals on the
# road are no step
NEAR = REJECT_LR
# ... or whose window's accepted parallaxes span this much (px): a step of this size is what
# the plane test (step_plane_px 0.5 px RMS: about 0.25 x the step across a 5 px window)
# refuses once sharpened, and walls steeper than 0.5 px/px qualify too. Seed-7 45° pair: the
# pothole's pixels spanning 2 px or more are 8 % of them and carry 42 % of its squared error
# (RMS 7.9 mm); MIN_SPAN_PX (0.5 px) selected half the image with the road's own relief, at 5x
# the matching's time, for no better surface
STEP_SPAN_PX = 4 * MIN_SPAN_PX
OWN_PX = 3  # the pixel's own neighbourhood that picks among the windows (px)
# Lucas-Kanade steps of the chosen window (count): it starts from its centre's first-pass
# parallax, a fraction of a pixel off
SHIFT_ITERS = 3


@dataclasses.dataclass
class _Match:
    s: torch.Tensor  # (N,) parallax (px)
    var: torch.Tensor  # (N,) its variance (px²)
    ncc: torch.Tensor  # (N,)
    grad: torch.Tensor  # (N,) RMS target gradient along ŵ in the window (DN/px)
    last: torch.Tensor  # (N,) last step (px)
    ok: torch.Tensor  # (N,) bool: inside, textured, converged, correlated


def _window_lk(
    ref: torch.Tensor,
    stack: torch.Tensor,
    ref_mask: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
    src: torch.Tensor,
    s0: torch.Tensor,
    win: int,
    cfg: DenseHeightConfig,
) -> _Match:
    """One parallax for each win x win window centred at the pixels ``src`` (N,) (flat
    indices) of ``ref`` (1, 1, H, W), from s0 (N,): Lucas-Kanade along ŵ with a local gain and
    offset against ``stack`` (1, 3, H, W: target, its gradient along ŵ, its inside mask)."""
    W = ref.shape[-1]
    dt = ref.dtype
    du, dv = window_offsets(win, ref.device)
    R, qi, inside = gather_windows(ref, src, win)
    ref_in = inside & (ref_mask.reshape(-1)[qi] >= INSIDE_MIN)
    xq = (src % W).to(dt)[:, None] + du
    yq = (src // W).to(dt)[:, None] + dv
    wq = (wx.reshape(-1)[qi], wy.reshape(-1)[qi])
    s, var, ncc, grad, last, n, w = window_lk(
        R, ref_in, xq, yq, wq, None, stack, s0, SHIFT_ITERS, cfg
    )
    tol = (cfg.step_max_sigma * var.sqrt()).clamp_min(STEP_MAX_PX)
    full = n >= w.shape[1] - 0.5  # the window wholly inside both images
    ok = full & (last <= tol) & (ncc >= cfg.min_ncc) & (grad >= cfg.min_grad_dn)
    ok &= torch.isfinite(s) & torch.isfinite(var)
    return _Match(s, var, ncc, grad, last, ok)


def _own_ncc(
    ref: torch.Tensor,
    tgt: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
    x: torch.Tensor,
    y: torch.Tensor,
    s: torch.Tensor,
) -> torch.Tensor:
    """(N,) ZNCC of the OWN_PX x OWN_PX pixels of ``ref`` around each pixel (x, y) (N,) with
    ``tgt`` at one parallax s (N,) along ŵ: how well the pixel's own neighbourhood agrees with
    that parallax."""
    H, W = ref.shape[-2:]
    dt = ref.dtype
    du, dv = window_offsets(OWN_PX, ref.device)
    xi = (x[:, None] + du.long()).clamp(0, W - 1)
    yi = (y[:, None] + dv.long()).clamp(0, H - 1)
    qi = yi * W + xi
    R = ref.reshape(-1)[qi]
    px = xi.to(dt) + s[:, None] * wx.reshape(-1)[qi]
    py = yi.to(dt) + s[:, None] * wy.reshape(-1)[qi]
    grid = torch.stack([px * (2.0 / (W - 1)) - 1.0, py * (2.0 / (H - 1)) - 1.0], -1)
    J = F.grid_sample(tgt, grid[None], mode="bilinear", align_corners=True)[0, 0]
    Rt, Jt = R - R.mean(1, keepdim=True), J - J.mean(1, keepdim=True)
    return (Rt * Jt).mean(1) / ((Rt * Rt).mean(1).sqrt() * (Jt * Jt).mean(1).sqrt() + 1e-3)


def shifted_refine(
    ref: torch.Tensor,
    tgt: torch.Tensor,
    tgt_mask: torch.Tensor,
    ref_mask: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
    first: RefineResult,
    flags: torch.Tensor,
    win: int,
    cfg: DenseHeightConfig,
) -> tuple[RefineResult, torch.Tensor]:
    """The shifted-window pass (module docstring) of the forward match ``first`` with its
    reject ``flags`` (1, 1, H, W uint8, 0 = accepted). Returns ``first`` with the replaced
    pixels' shift, variance, ZNCC, texture and last step, and the (1, 1, H, W) bool mask of the
    replaced pixels. Images and fields as in ``matching.refine``."""
    H, W = ref.shape[-2:]
    dt = ref.dtype
    ok0 = flags == 0
    near = window_max(((flags & NEAR) != 0).to(dt), win) > 0
    big = torch.tensor(1e6, device=ref.device, dtype=dt)
    hi = window_max(torch.where(ok0, first.shift, -big), win)
    lo = window_min(torch.where(ok0, first.shift, big), win)
    sel = ok0 & (near | (hi - lo >= STEP_SPAN_PX))
    idx = torch.nonzero(sel[0, 0].reshape(-1)).squeeze(1)
    mask = torch.zeros_like(ok0).reshape(-1)
    if idx.numel() == 0:
        return first, mask.reshape(ok0.shape)
    x, y = idx % W, idx // W
    s_first = first.shift.reshape(-1)[idx]
    own_first = _own_ncc(ref, tgt, wx, wy, x, y, s_first)
    best_own = own_first.clone()
    best_src = torch.full_like(idx, -1)
    r = win // 2
    okf = ok0.reshape(-1)
    for dv in (-r, 0, r):
        for du in (-r, 0, r):
            if du == 0 and dv == 0:
                continue
            cx, cy = x + du, y + dv
            inside = (cx >= 0) & (cx < W) & (cy >= 0) & (cy < H)
            c = cy.clamp(0, H - 1) * W + cx.clamp(0, W - 1)
            s = first.shift.reshape(-1)[c]  # the window's own match
            own = _own_ncc(ref, tgt, wx, wy, x, y, s)
            take = inside & okf[c] & torch.isfinite(s) & (own > best_own)
            best_own = torch.where(take, own, best_own)
            best_src = torch.where(take, c, best_src)
    take = best_src >= 0
    jj, src = idx[take], best_src[take]
    # the chosen window matched on its own (one parallax, Lucas-Kanade from its centre's)
    gx, gy = gradients(tgt)
    stack = torch.cat([tgt, gx * wx + gy * wy, tgt_mask.to(dt)], 1)
    m = _window_lk(ref, stack, ref_mask, wx, wy, src, first.shift.reshape(-1)[src], win, cfg)
    s_new = m.s
    keep = m.ok & (_own_ncc(ref, tgt, wx, wy, x[take], y[take], s_new) > own_first[take])
    jj = jj[keep]
    names = ("shift", "var", "ncc", "grad", "last_step")
    out = {k: getattr(first, k).clone().reshape(-1) for k in names}
    for k, val in zip(names, (s_new, m.var, m.ncc, m.grad, m.last), strict=True):
        out[k][jj] = val[keep].to(out[k].dtype)
    mask[jj] = True
    log.debug("dense: shifted windows on %d px, %d replaced", idx.numel(), int(jj.numel()))
    shape = first.shift.shape
    new = dataclasses.replace(first, **{k: v.reshape(shape) for k, v in out.items()})
    return new, mask.reshape(shape)
