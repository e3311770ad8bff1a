"""Dense 1D matching along the epipolar lines of a plane-warped pair, in torch (the same code on
CPU and CUDA): a ZNCC plane sweep over heights above the road (``sweep``) and a 1D
Lucas-Kanade refinement of the parallax with its variance (``refine``).

Images are (1, 1, H, W) float32 tensors in DN; ``ref`` is the image whose pixels are measured,
``tgt`` the one searched (sampled at ref pixel + s ŵ). Fields (direction, shifts) are (1, 1, H, W)
tensors on the same grid.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F


def box(x: torch.Tensor, win: int) -> torch.Tensor:
    """Mean over a win x win window, borders averaged over the pixels inside the image. On the
    CPU through OpenCV (an order of magnitude faster than torch's pooling there), the same
    numbers up to float rounding."""
    if x.device.type != "cpu":
        return F.avg_pool2d(x, win, stride=1, padding=win // 2, count_include_pad=False)
    a = x.detach().numpy()
    out = np.empty_like(a)
    k = (win, win)
    cnt = cv2.boxFilter(
        np.ones(a.shape[-2:], np.float32), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            s = cv2.boxFilter(a[i, j], -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
            out[i, j] = s / cnt
    return torch.from_numpy(out)


def window_max(x: torch.Tensor, win: int) -> torch.Tensor:
    """Maximum over a win x win window (OpenCV's dilation on the CPU, max pooling elsewhere)."""
    if x.device.type != "cpu":
        return F.max_pool2d(x, win, stride=1, padding=win // 2)
    a = x.detach().numpy()
    out = np.empty_like(a)
    k = np.ones((win, win), np.uint8)
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            out[i, j] = cv2.dilate(a[i, j], k, borderType=cv2.BORDER_REPLICATE)
    return torch.from_numpy(out)


def sample(img: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of img (1, C, H, W) at pixel coordinates x, y (1, 1, h, w); zeros
    outside (callers track validity with a sampled mask)."""
    H, W = img.shape[-2:]
    grid = torch.stack([x[0, 0] * (2.0 / (W - 1)) - 1.0, y[0, 0] * (2.0 / (H - 1)) - 1.0], -1)
    return F.grid_sample(img, grid[None], mode="bilinear", padding_mode="zeros", align_corners=True)


def gaussian(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur (σ in px; reflect borders); identity for σ <= 0."""
    if sigma <= 0:
        return x
    r = max(1, int(round(3 * sigma)))
    if x.device.type == "cpu":  # OpenCV: faster on the CPU; BORDER_REFLECT_101 = torch's reflect
        a = x.detach().numpy()
        out = np.empty_like(a)
        for i in range(a.shape[0]):
            for j in range(a.shape[1]):
                out[i, j] = cv2.GaussianBlur(
                    a[i, j], (2 * r + 1, 2 * r + 1), sigma, borderType=cv2.BORDER_REFLECT_101
                )
        return torch.from_numpy(out)
    k = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-0.5 * (k / sigma) ** 2)
    k = k / k.sum()
    x = F.pad(x, (r, r, r, r), mode="reflect")
    x = F.conv2d(x, k.view(1, 1, 1, -1))
    return F.conv2d(x, k.view(1, 1, -1, 1))


def gradients(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central-difference gradients d/dx, d/dy (DN/px), one-sided at the borders."""
    gx = torch.zeros_like(x)
    gy = torch.zeros_like(x)
    gx[..., 1:-1] = 0.5 * (x[..., 2:] - x[..., :-2])
    gx[..., 0] = x[..., 1] - x[..., 0]
    gx[..., -1] = x[..., -1] - x[..., -2]
    gy[..., 1:-1, :] = 0.5 * (x[..., 2:, :] - x[..., :-2, :])
    gy[..., 0, :] = x[..., 1, :] - x[..., 0, :]
    gy[..., -1, :] = x[..., -1, :] - x[..., -2, :]
    return gx, gy


@dataclass
class SweepResult:
    value: torch.Tensor  # (1, 1, H, W) swept quantity at the ZNCC peak, sub-step (parabola)
    ncc: torch.Tensor  # (1, 1, H, W) ZNCC at the best step
    interior: torch.Tensor  # (1, 1, H, W) bool: the peak is not at either end of the sweep


def sweep(
    ref: torch.Tensor,
    tgt: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
    values: torch.Tensor,
    shift_of: Callable[[torch.Tensor], torch.Tensor],
    win: int,
) -> SweepResult:
    """ZNCC sweep: for each candidate ``values[k]`` (a height, m) the target is sampled at ref
    pixel + shift_of(values[k]) ŵ (shift_of gives the (1, 1, H, W) parallax field in px) and
    compared with ref in win x win windows. Memory O(H W): only the running best and its two
    neighbours' scores are kept; the peak is refined by a parabola through them."""
    H, W = ref.shape[-2:]
    dev, dt = ref.device, ref.dtype
    ys, xs = torch.meshgrid(
        torch.arange(H, device=dev, dtype=dt), torch.arange(W, device=dev, dtype=dt), indexing="ij"
    )
    xs, ys = xs[None, None], ys[None, None]
    mu_r = box(ref, win)
    sd_r = (box(ref * ref, win) - mu_r * mu_r).clamp_min(0).sqrt()
    best = torch.full_like(ref, -2.0)
    left = torch.full_like(ref, -2.0)
    right = torch.full_like(ref, -2.0)
    idx = torch.zeros_like(ref, dtype=torch.long)
    prev = torch.full_like(ref, -2.0)
    just = torch.zeros_like(ref, dtype=torch.bool)  # best set at the previous step
    for k in range(len(values)):
        s = shift_of(values[k])
        J = sample(tgt, xs + s * wx, ys + s * wy)
        mu_j = box(J, win)
        cov = box(ref * J, win) - mu_r * mu_j
        sd_j = (box(J * J, win) - mu_j * mu_j).clamp_min(0).sqrt()
        c = cov / (sd_r * sd_j + 1e-3)
        right = torch.where(just, c, right)
        up = c > best
        best = torch.where(up, c, best)
        left = torch.where(up, prev, left)
        idx = torch.where(up, torch.full_like(idx, k), idx)
        just = up
        prev = c
    n = len(values)
    interior = (idx > 0) & (idx < n - 1)
    den = left - 2 * best + right
    off = torch.where(interior & (den < -1e-6), 0.5 * (left - right) / den, torch.zeros_like(den))
    off = off.clamp(-0.5, 0.5)
    step = (values[-1] - values[0]) / max(n - 1, 1)
    value = values[0] + (idx.to(dt) + off) * step
    return SweepResult(value, best, interior)


@dataclass
class RefineResult:
    shift: torch.Tensor  # (1, 1, H, W) parallax along ŵ (px)
    var: torch.Tensor  # (1, 1, H, W) its variance (px²)
    ncc: torch.Tensor  # (1, 1, H, W) ZNCC of the windows at the final parallax
    grad: torch.Tensor  # (1, 1, H, W) RMS gradient of the target along ŵ in the window (DN/px)
    last_step: torch.Tensor  # (1, 1, H, W) |last update| (px): not converged when large
    inside: torch.Tensor  # (1, 1, H, W) share of the window's samples inside the target (0-1)


def refine(
    ref: torch.Tensor,
    tgt: torch.Tensor,
    tgt_mask: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
    shift: torch.Tensor,
    win: int,
    iters: int,
    noise_dn: float,
) -> RefineResult:
    """1D Lucas-Kanade along ŵ with a local gain and offset: in each window
    ref - μ_ref ≈ g (tgt(x + s ŵ) - μ_tgt) with g = σ_ref / σ_tgt. Every pixel samples the
    target at its own parallax s_i, so the window of x is linearised about its pixels' s_i:
    tgt_i(s) ≈ J_i + G_i (s - s_i), and the Gauss-Newton solution of the window is

        s(x) = [Σ G̃_i r_i / g + Σ G̃_i² s_i] / Σ G̃_i²,   r_i = ref̃_i - g J̃_i

    (tildes: minus the window's mean; window sums by box filters). Adding the update to s(x)
    alone (Σ G̃ r / Σ G̃²) would treat the neighbours as if they were at s(x); that
    iteration amplifies checkerboard errors and diverges. The variance is the LK one:
    σ_r² / (n g² var(∂tgt/∂ŵ)), σ_r² the window's residual variance (2 σ_ref² (1 - ZNCC)),
    never below the noise of two images (2 noise_dn²)."""
    H, W = ref.shape[-2:]
    dev, dt = ref.device, ref.dtype
    ys, xs = torch.meshgrid(
        torch.arange(H, device=dev, dtype=dt), torch.arange(W, device=dev, dtype=dt), indexing="ij"
    )
    xs, ys = xs[None, None], ys[None, None]
    # the target's gradient along ŵ, taken on its own grid (ŵ turns by s / (distance to the
    # epipole) between a pixel and its match: well under 1% where pixels are kept), sampled with
    # the image: two channels per step instead of four
    gx, gy = gradients(tgt)
    stack = torch.cat([tgt, gx * wx + gy * wy], dim=1)
    mu_r = box(ref, win)
    var_r = (box(ref * ref, win) - mu_r * mu_r).clamp_min(0)
    s = shift.clone()
    last = torch.zeros_like(s)
    for it in range(iters + 1):
        px, py = xs + s * wx, ys + s * wy
        smp = sample(stack, px, py)
        J, G = smp[:, :1], smp[:, 1:2]
        m = box(torch.cat([J, G, J * J, G * G, ref * G, J * G], dim=1), win)
        mu_j, mu_g = m[:, :1], m[:, 1:2]
        var_j = (m[:, 2:3] - mu_j * mu_j).clamp_min(1e-6)
        var_g = (m[:, 3:4] - mu_g * mu_g).clamp_min(1e-9)
        cov_rg = m[:, 4:5] - mu_r * mu_g
        cov_jg = m[:, 5:6] - mu_j * mu_g
        g = (var_r / var_j).sqrt().clamp(0.5, 2.0)
        if it == iters:
            break
        ms = box(torch.cat([s, G * s, G * G * s], dim=1), win)
        ggs = ms[:, 2:3] - 2 * mu_g * ms[:, 1:2] + mu_g * mu_g * ms[:, :1]
        s_new = ((cov_rg - g * cov_jg) / g + ggs) / var_g
        d = (s_new - s).clamp(-1.0, 1.0)
        last = d.abs()
        s = s + d
    cov_rj = box(ref * J, win) - mu_r * mu_j
    ncc = cov_rj / (var_r.sqrt() * var_j.sqrt() + 1e-3)
    res = (2.0 * var_r * (1.0 - ncc)).clamp_min(2.0 * noise_dn * noise_dn)
    var = res / (win * win * g * g * var_g)
    inside = box(sample(tgt_mask, px, py), win)
    return RefineResult(s, var, ncc, var_g.sqrt(), last, inside)
