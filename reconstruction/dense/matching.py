"""Dense 1D matching along the epipolar lines of a plane-warped pair, in torch (the same code on
CPU and CUDA): a ZNCC plane sweep over heights above the road (``sweep``) and a 1D
Lucas-Kanade refinement of the parallax with its variance (``refine``).

Images are (1, 1, H, W) float32 tensors in DN; ``ref`` is the image whose pixels are measured,
``tgt`` the one searched (sampled at ref pixel + s ŵ). Fields (direction, shifts) are (1, 1, H, W)
tensors on the same grid.
"""

from __future__ import annotations

import functools
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
    return _box_cpu([a[i, j] for i in range(a.shape[0]) for j in range(a.shape[1])], win).view(
        x.shape
    )


def box_stack(
    parts: list[torch.Tensor], win: int, over: torch.Tensor | None = None
) -> torch.Tensor:
    """``box(torch.cat(parts, 1), win)`` for (1, 1, H, W) parts, divided by ``over`` (1, 1, H,
    W) when given, without the concatenation: on the CPU each part is filtered straight into its
    channel of the (1, len(parts), H, W) result and the divisions are done in place (the same
    numbers)."""
    if parts[0].device.type != "cpu":
        m = box(torch.cat(parts, 1), win)
        return m if over is None else m / over
    div = None if over is None else over.detach().numpy()[0]
    return _box_cpu([p.detach().numpy()[0, 0] for p in parts], win, div)[None]


def _box_cpu(planes: list[np.ndarray], win: int, div: np.ndarray | None = None) -> torch.Tensor:
    """(len(planes), H, W) window means of the (H, W) float32 planes (OpenCV's unnormalised box
    filter into each channel, then one division by the window's pixel count inside the grid),
    divided by ``div`` (1, H, W) when given."""
    h, w = planes[0].shape
    out = np.empty((len(planes), h, w), np.float32)
    k = (win, win)
    for i, a in enumerate(planes):
        cv2.boxFilter(a, -1, k, dst=out[i], normalize=False, borderType=cv2.BORDER_CONSTANT)
    np.divide(out, _inside_count(h, w, win).numpy(), out=out)
    if div is not None:
        np.divide(out, div, out=out)
    return torch.from_numpy(out)


@functools.lru_cache(maxsize=8)
def _inside_count(h: int, w: int, win: int) -> torch.Tensor:
    """(H, W) float32 number of pixels of the win x win window inside an H x W grid (exact
    integers; cached for the next calls on the same grid: private, never handed out)."""
    cnt = cv2.boxFilter(
        np.ones((h, w), np.float32), -1, (win, win), normalize=False,
        borderType=cv2.BORDER_CONSTANT,
    )  # fmt: skip
    return torch.from_numpy(cnt)


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


def window_min(x: torch.Tensor, win: int) -> torch.Tensor:
    """Minimum over a win x win window: ``-window_max(-x, win)`` (OpenCV's erosion on the CPU)."""
    if x.device.type != "cpu":
        return -F.max_pool2d(-x, win, stride=1, padding=win // 2)
    a = x.detach().numpy()
    out = np.empty_like(a)
    k = np.ones((win, win), np.uint8)
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            cv2.erode(a[i, j], k, dst=out[i, j], borderType=cv2.BORDER_REPLICATE)
    return torch.from_numpy(out)


def sample(img: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of img (1, C, H, W) at pixel coordinates x, y (N, 1, h, w) -> (N, C, h,
    w) (N = 1 but in the sweep's batches); zeros outside (callers track validity with a sampled
    mask)."""
    H, W = img.shape[-2:]
    n = x.shape[0]
    # normalised coordinates written straight into the interleaved grid (torch.stack along the
    # last axis cost 10x these three operations)
    grid = torch.empty((n, *x.shape[-2:], 2), dtype=x.dtype, device=x.device)
    torch.mul(x[:, 0], 2.0 / (W - 1), out=grid[..., 0])
    torch.mul(y[:, 0], 2.0 / (H - 1), out=grid[..., 1])
    grid.sub_(1.0)
    if img.shape[0] != n:
        img = img.expand(n, -1, -1, -1)
    return F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


def sample_along(
    img: torch.Tensor,
    xs: torch.Tensor,
    ys: torch.Tensor,
    s: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
) -> torch.Tensor:
    """``sample(img, xs + s * wx, ys + s * wy)``: img (1, C, H, W) at the pixels xs, ys moved by
    s along ŵ (all (1, 1, h, w); s may be a batch (N, 1, h, w)), the same numbers with fewer
    temporaries."""
    px = s * wx
    px.add_(xs)
    py = s * wy
    py.add_(ys)
    return sample(img, px, py)


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


INSIDE_MIN = 0.999  # a bilinear sample of a 0/1 mask at least this is inside the image (−)


def inside_weight(tgt_inside: torch.Tensor, ref_mask: torch.Tensor | None) -> torch.Tensor:
    """(1, 1, H, W) float 0/1 weight of each window sample: 1 where the target's sampled mask
    (bilinear, ``tgt_inside``) is at least ``INSIDE_MIN`` (its four neighbours are image data)
    and ``ref_mask`` (None: everywhere) marks the reference pixel as image data."""
    w = (tgt_inside >= INSIDE_MIN).to(tgt_inside.dtype)
    return w if ref_mask is None else w * (ref_mask >= INSIDE_MIN).to(w.dtype)


def window_count(h: int, w: int, win: int, device: torch.device) -> torch.Tensor:
    """(1, 1, h, w) number of pixels of the win x win window inside an h x w grid (``box``
    averages over these)."""
    if device.type == "cpu":  # the same numbers as the pooling below (its mean, times win²)
        return _inside_count(h, w, win)[None, None] / (win * win) * (win * win)
    r = win // 2
    ones = torch.ones((1, 1, h, w), device=device)
    return F.avg_pool2d(ones, win, stride=1, padding=r, count_include_pad=True) * (win * win)


# candidates of the sweep evaluated together (count): a batch's operations run once for all of
# them (the sweep grid is small, ~0.02 Mpx: per-call overhead dominated); memory K x the grid
SWEEP_BATCH = 8


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
    tgt_mask: torch.Tensor | None = None,
    ref_mask: torch.Tensor | None = None,
) -> SweepResult:
    """ZNCC sweep: for each candidate ``values[k]`` (a height, m) the target is sampled at ref
    pixel + shift_of(values[k]) ŵ (shift_of gives the (1, 1, H, W) parallax field in px; it is
    called with ``SWEEP_BATCH`` heights at a time, as a (K, 1, 1, 1) tensor, and must broadcast
    them to (K, 1, H, W)) and compared with ref in win x win windows. Memory O(K H W): only the
    batch's scores, the running best and its two neighbours' scores are kept; the peak is
    refined by a parabola through them.

    With ``tgt_mask`` (1, 1, H, W), 1 where tgt holds image data, and ``ref_mask`` (the same for
    ref), a window's ZNCC uses only its samples inside both images (``inside_weight``): a window
    that crosses the edge of the overlap correlates its part that both images see, instead of
    the zeros beyond the edge."""
    H, W = ref.shape[-2:]
    dev, dt = ref.device, ref.dtype
    ys, xs = torch.meshgrid(
        torch.arange(H, device=dev, dtype=dt), torch.arange(W, device=dev, dtype=dt), indexing="ij"
    )
    xs, ys = xs[None, None], ys[None, None]
    masked = tgt_mask is not None
    mu_r = box(ref, win)
    sd_r = (box(ref * ref, win) - mu_r * mu_r).clamp_min(0).sqrt()
    tgt_stack = torch.cat([tgt, tgt_mask], dim=1) if tgt_mask is not None else tgt
    best = torch.full_like(ref, -2.0)
    left = torch.full_like(ref, -2.0)
    right = torch.full_like(ref, -2.0)
    idx = torch.zeros_like(ref, dtype=torch.long)
    prev = torch.full_like(ref, -2.0)
    just = torch.zeros_like(ref, dtype=torch.bool)  # best set at the previous step
    if masked:
        # a candidate whose window has mostly left image b correlates a few samples, and 2-5
        # samples give a ZNCC near ±1 that beats the true match: it needs at least a corner
        # window's samples ((win // 2 + 1)², 9 of 25; the match itself is held to
        # ``checks.min_window_samples`` after refinement)
        n_grid = window_count(H, W, win, dev).to(dt)
        min_n = float((win // 2 + 1) ** 2)
        rw = None if ref_mask is None else (ref_mask >= INSIDE_MIN).to(dt)
    n = len(values)
    for k0 in range(0, n, SWEEP_BATCH):
        # SWEEP_BATCH candidates at once (each one's numbers as if alone): shift_of receives
        # their heights as a (K, 1, 1, 1) tensor and broadcasts them to (K, 1, H, W)
        s = shift_of(values[k0 : k0 + SWEEP_BATCH].view(-1, 1, 1, 1))
        smp = sample_along(tgt_stack, xs, ys, s, wx, wy)
        J = smp[:, :1]
        if masked:
            wgt = (smp[:, 1:2] >= INSIDE_MIN).to(dt)  # ``inside_weight``
            if rw is not None:
                wgt.mul_(rw)
            wr, wj = wgt * ref, wgt * J
            m = box(torch.cat([wgt, wr, wr * ref, wj, wj * J, wr * J], 1), win)
            enough = m[:, :1] * n_grid >= min_n - 0.5
            m = m[:, 1:].div_(m[:, :1].clamp_min(1e-6))
            mu_rw, mu_j = m[:, :1], m[:, 2:3]
            sd_rw = torch.sub(m[:, 1:2], mu_rw * mu_rw).clamp_min_(0).sqrt_()
            sd_j = torch.sub(m[:, 3:4], mu_j * mu_j).clamp_min_(0).sqrt_()
            c = torch.sub(m[:, 4:5], mu_rw * mu_j).div_(sd_rw.mul_(sd_j).add_(1e-3))
            c.masked_fill_(~enough, -2.0)
        else:
            mu_j = box(J, win)
            cov = box(ref * J, win) - mu_r * mu_j
            sd_j = (box(J * J, win) - mu_j * mu_j).clamp_min(0).sqrt()
            c = cov / (sd_r * sd_j + 1e-3)
        for j in range(c.shape[0]):  # the running best, candidate by candidate
            cj = c[j : j + 1]
            right = torch.where(just, cj, right)
            up = cj > best
            best = torch.where(up, cj, best)
            left = torch.where(up, prev, left)
            idx.masked_fill_(up, k0 + j)
            just = up
            prev = cj
    interior = (idx > 0) & (idx < n - 1)
    den = left - 2 * best + right
    off = torch.where(interior & (den < -1e-6), 0.5 * (left - right) / den, torch.zeros_like(den))
    off = off.clamp(-0.5, 0.5)
    step = (values[-1] - values[0]) / max(n - 1, 1)
    value = values[0] + (idx.to(dt) + off) * step
    return SweepResult(value, best, interior)


def fill_unswept(value: torch.Tensor, ncc: torch.Tensor, steps: int) -> torch.Tensor:
    """``value`` (1, 1, H, W) where the sweep had no candidate with enough samples (``ncc`` -2,
    a band along the edge of the overlap) replaced by the mean of its swept neighbours, grown
    outwards by one pixel a step for ``steps`` steps: a start for the refinement there, which
    keeps only matches that pass its own checks (samples, ZNCC, left-right). Such pixels
    otherwise started at the sweep's first value (the deepest height) and never converged."""
    ok = (ncc > -1.5).to(value.dtype)
    v = torch.where(ok > 0, value, torch.zeros_like(value))
    for _ in range(max(int(steps), 0)):
        if bool(ok.min() > 0):
            break
        m = box(torch.cat([ok, v * ok], 1), 3)
        grow = (ok == 0) & (m[:, :1] > 0)
        v = torch.where(grow, m[:, 1:2] / m[:, :1].clamp_min(1e-6), v)
        ok = torch.where(grow, torch.ones_like(ok), ok)
    return torch.where(ok > 0, v, value)


@dataclass
class RefineResult:
    shift: torch.Tensor  # (1, 1, H, W) parallax along ŵ (px)
    var: torch.Tensor  # (1, 1, H, W) its variance (px²)
    ncc: torch.Tensor  # (1, 1, H, W) ZNCC of the windows at the final parallax
    grad: torch.Tensor  # (1, 1, H, W) RMS gradient of the target along ŵ in the window (DN/px)
    last_step: torch.Tensor  # (1, 1, H, W) |last update| (px): not converged when large
    # (1, 1, H, W) samples of the window inside both images at the final parallax (count; the
    # window's pixels inside the grid, win² away from its border, where all are inside)
    samples: torch.Tensor
    centre: torch.Tensor  # (1, 1, H, W) bool: the pixel's own sample is inside both images


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
    ref_mask: torch.Tensor | None = None,
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
    never below the noise of two images (2 noise_dn²).

    Every sum runs over the window's samples inside both images only (``inside_weight``: the
    target's mask ``tgt_mask`` sampled at the current parallax, ``ref_mask`` at the pixel;
    n = their count): next to the edge of the overlap the window is the part of it that both
    images see, as ``box`` already clips it at the grid's own border, instead of a window that
    reads the zeros beyond the edge. Where every sample is inside, the sums are the plain ones."""
    H, W = ref.shape[-2:]
    dev, dt = ref.device, ref.dtype
    ys, xs = torch.meshgrid(
        torch.arange(H, device=dev, dtype=dt), torch.arange(W, device=dev, dtype=dt), indexing="ij"
    )
    xs, ys = xs[None, None], ys[None, None]
    # the target's gradient along ŵ, taken on its own grid (ŵ turns by s / (distance to the
    # epipole) between a pixel and its match: well under 1% where pixels are kept), sampled with
    # the image and its mask: three channels per step instead of five
    gx, gy = gradients(tgt)
    stack = torch.cat([tgt, gx * wx + gy * wy, tgt_mask.to(dt)], dim=1)
    r2 = ref * ref
    rw = None if ref_mask is None else (ref_mask >= INSIDE_MIN).to(dt)  # ``inside_weight``'s
    s = shift.clone()
    last = torch.zeros_like(s)
    wgt = torch.ones_like(s)
    # the window sums of the reference alone (the weights, ref and ref², and what follows from
    # them) change only when a sample leaves the window: while the weights stay the same they
    # are kept from the step before (the same numbers, a third fewer box channels)
    w_prev: torch.Tensor | None = None
    # in-place arithmetic below: each result the same as the plain expression in the comment
    for it in range(iters + 1):
        smp = sample_along(stack, xs, ys, s, wx, wy)
        J, G = smp[:, :1], smp[:, 1:2]
        w_now = (smp[:, 2:3] >= INSIDE_MIN).to(dt)
        if rw is not None:
            w_now.mul_(rw)
        wgt = w_now if it == iters else w_now.mul_(wgt)  # wgt * w_now
        wJ, wG = wgt * J, wgt * G
        wGG = wG * G
        if w_prev is None or not torch.equal(wgt, w_prev):
            mr = box_stack([wgt, wgt * ref, wgt * r2], win)
            share = mr[:, :1]
            share_c = share.clamp_min(1e-6)
            mu_r = mr[:, 1:2] / share_c
            var_r = (mr[:, 2:3] / share_c).sub_(mu_r * mu_r).clamp_min_(0)
            w_prev = wgt
        m = box_stack([wJ, wG, wJ * J, wGG, wG * ref, wJ * G], win, over=share_c)
        mu_j, mu_g = m[:, :1], m[:, 1:2]
        mu_gg = mu_g * mu_g
        var_j = torch.sub(m[:, 2:3], mu_j * mu_j).clamp_min_(1e-6)
        var_g = torch.sub(m[:, 3:4], mu_gg).clamp_min_(1e-9)
        cov_rg = torch.sub(m[:, 4:5], mu_r * mu_g)
        cov_jg = torch.sub(m[:, 5:6], mu_j * mu_g)
        g = torch.div(var_r, var_j).sqrt_().clamp_(0.5, 2.0)
        if it == iters:
            break
        ms = box_stack([wgt * s, wG * s, wGG * s], win, over=share_c)
        # ggs = ms[:, 2:3] - 2 * mu_g * ms[:, 1:2] + mu_g * mu_g * ms[:, :1]
        ggs = torch.mul(mu_g, 2).mul_(ms[:, 1:2])
        torch.sub(ms[:, 2:3], ggs, out=ggs)
        ggs.add_(mu_gg.mul_(ms[:, :1]))
        # d = (((cov_rg - g * cov_jg) / g + ggs) / var_g - s).clamp(-1, 1)
        d = torch.mul(g, cov_jg)
        torch.sub(cov_rg, d, out=d)
        d.div_(g).add_(ggs).div_(var_g).sub_(s).clamp_(-1.0, 1.0)
        last = d.abs()
        s = s + d
    cov_rj = box(wgt * ref * J, win) / share_c - mu_r * mu_j
    ncc = cov_rj / (var_r.sqrt() * var_j.sqrt() + 1e-3)
    n = share * window_count(H, W, win, dev)
    res = (2.0 * var_r * (1.0 - ncc)).clamp_min(2.0 * noise_dn * noise_dn)
    var = res / (n.clamp_min(1.0) * g * g * var_g)
    return RefineResult(s, var, ncc, var_g.sqrt(), last, n, wgt > 0.5)
