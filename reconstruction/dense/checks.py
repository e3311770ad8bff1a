"""The checks a dense match must pass, as reject flags (``REJECT_*`` bits, 0 = kept): which test
refused a pixel is kept with the heights (``DenseHeight.reject``), so that a loss of coverage can
be traced to its cause (``benchmarks.dense_floor``)."""

from __future__ import annotations

import torch

from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.matching import (
    INSIDE_MIN,
    RefineResult,
    inside_weight,
    sample_along,
    window_max,
    window_min,
)

REJECT_OUTSIDE = 1  # the pixel, or too much of its window, outside image a or its match in b
REJECT_TEXTURE = 2  # RMS gradient along the epipolar line below min_grad_dn
REJECT_NCC = 4  # ZNCC below min_ncc
REJECT_STEP = 8  # Lucas-Kanade not converged (last step > 0.05 px and > step_max_sigma σ)
REJECT_EXPOSURE = 16  # a dark or saturated pixel in either window
REJECT_LR = 32  # the b -> a match disagrees by more than lr_max_px
REJECT_GEOMETRY = 64  # non-finite, next to the epipole, or outside the searched heights
REJECT_UNMATCHED = 128  # outside the part of image a that image b sees (not matched)
REJECT_NAMES = {
    REJECT_OUTSIDE: "outside",
    REJECT_TEXTURE: "texture",
    REJECT_NCC: "ncc",
    REJECT_STEP: "step",
    REJECT_EXPOSURE: "exposure",
    REJECT_LR: "lr",
    REJECT_GEOMETRY: "geometry",
    REJECT_UNMATCHED: "unmatched",
}

STEP_MAX_PX = 0.05  # a last Lucas-Kanade step above this is not converged (px)


def min_window_samples(win: int) -> int:
    """Fewest samples of a win x win window that a match may rest on: a window centred on a
    straight edge of the overlap, (win // 2 + 1) x win (15 of 25 for 5 px), which is what
    ``matching.box`` has always used at the grid's own border. A pixel on the edge keeps its
    height; a corner's (9 of 25) or a pixel outside the overlap does not."""
    return (win // 2 + 1) * win


def checks(
    cfg: DenseHeightConfig,
    fwd: RefineResult,
    mAt: torch.Tensor,
    mBt: torch.Tensor,
    A_raw: torch.Tensor,
    B_raw: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
    win: int,
) -> torch.Tensor:
    """(1, 1, h, w) uint8 reject flags of the forward match (0: textured, well exposed,
    correlated, converged, its own sample and at least ``min_window_samples`` of its window
    inside both images). mAt, mBt: where image a's and b's resamplings lie inside their images
    (0/1); A_raw, B_raw: the unblurred resampled images (DN); wx, wy: the epipolar direction;
    win: the window's side (px)."""

    def flag(bad: torch.Tensor, bit: int) -> torch.Tensor:
        return bad.to(torch.uint8) * bit

    f = flag(~fwd.centre | (fwd.samples < min_window_samples(win) - 0.5), REJECT_OUTSIDE)
    f |= flag(~(fwd.grad >= cfg.min_grad_dn), REJECT_TEXTURE)
    f |= flag(~(fwd.ncc >= cfg.min_ncc), REJECT_NCC)
    if cfg.refine_iters > 0:
        tol = (cfg.step_max_sigma * fwd.var.sqrt()).clamp_min(STEP_MAX_PX)
        f |= flag(~(fwd.last_step <= tol), REJECT_STEP)
    # saturated or black windows in either image (b sampled at the match)
    hw, ww = A_raw.shape[-2:]
    ys, xs = torch.meshgrid(
        torch.arange(hw, device=A_raw.device, dtype=torch.float32),
        torch.arange(ww, device=A_raw.device, dtype=torch.float32),
        indexing="ij",
    )
    Bm = sample_along(torch.cat([B_raw, mBt], 1), xs[None, None], ys[None, None], fwd.shift, wx, wy)
    # samples outside an image (not in the window's sums) read as mid-grey here
    grey = 0.5 * (cfg.dark_dn + cfg.saturated_dn)
    Bm = torch.where(inside_weight(Bm[:, 1:2], mAt) > 0.5, Bm[:, :1], grey)
    Am = torch.where(mAt >= INSIDE_MIN, A_raw, grey)
    for img in (Am, Bm):
        hi = window_max(img, win)
        lo = window_min(img, win)
        f |= flag(~((hi < cfg.saturated_dn) & (lo > cfg.dark_dn)), REJECT_EXPOSURE)
    f |= flag(~(torch.isfinite(fwd.shift) & torch.isfinite(fwd.var)), REJECT_GEOMETRY)
    return f
