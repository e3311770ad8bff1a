"""The slanted second pass of the dense match (reconstruction.dense.slanted) on a seeded
synthetic pair with an exact parallax field: a flat road, a steep wall (the parallax rising
linearly across 20 px) and a raised floor, the target image rendered from the reference
texture through that field."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.matching import refine
from roadsurf.reconstruction.dense.slanted import parallax_gradient, plane_fit, slanted_refine

H, W = 96, 160
U0, U1 = 60.0, 80.0  # the wall's columns (px)
SS = 8  # texture supersampling


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float32)[None, None]


def _pair(slope: float, seed: int) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Reference, target (1, 1, H, W) DN and the true parallax along +u (H, W) px: zero left
    of the wall, ``slope`` px/px across it, constant right of it; 1 DN noise on the target."""
    rng = np.random.default_rng(seed)
    big = np.zeros((H * SS, W * SS), np.float32)
    for sig, amp in ((1.0, 1.0), (2.0, 1.0), (4.0, 0.6)):
        n = rng.standard_normal(big.shape).astype(np.float32)
        big += amp * cv2.GaussianBlur(n, (0, 0), sig * SS)
    big = 128 + 40 * big / big.std()

    def tex(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        mu, mv = (
            ((u + 0.5) * SS - 0.5).astype(np.float32),
            ((v + 0.5) * SS - 0.5).astype(np.float32),
        )
        return cv2.remap(big, mu, mv, cv2.INTER_LINEAR)

    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    s_true = np.clip(u - U0, 0, U1 - U0) * slope
    top = U1 + slope * (U1 - U0)  # where the wall's far edge lands in the target
    # the reference pixel u lands at u + s(u) in the target: invert it per target column
    u_src = np.where(
        u < U0, u, np.where(u < top, U0 + (u - U0) / (1 + slope), u - slope * (U1 - U0))
    )
    tgt = tex(u_src, v) + rng.normal(0, 1.0, (H, W)).astype(np.float32)
    return _t(tex(u, v)), _t(tgt), s_true


@pytest.mark.parametrize(("slope", "seed"), [(0.4, 0), (0.8, 1)])
def test_slanted_windows_recover_a_steep_wall(slope: float, seed: int) -> None:
    ref, tgt, s_true = _pair(slope, seed)
    ones = torch.ones_like(ref)
    wx, wy = ones, torch.zeros_like(ref)
    init = _t(cv2.blur(s_true.astype(np.float32), (9, 9)))  # a blurred start, like the sweep's
    cfg = DenseHeightConfig(device="cpu")
    first = refine(ref, tgt, ones, wx, wy, init, 5, 5, 1.0, ones)
    valid = (first.ncc >= cfg.min_ncc) & (first.last_step <= 0.05 + 0.5 * first.var.sqrt())
    second, replaced = slanted_refine(ref, tgt, ones, ones, wx, wy, first, valid, 5, cfg)
    wall = np.zeros((H, W), bool)
    wall[8:-8, int(U0) + 3 : int(U1) - 2] = True  # inside the ramp, off its two kinks
    flat = np.zeros((H, W), bool)
    flat[8:-8, 10:50] = True
    ok = valid[0, 0].numpy()
    assert ok[wall].mean() > 0.8

    def rms(r: torch.Tensor, m: np.ndarray) -> float:
        e = r.shift[0, 0].numpy() - s_true
        return float(np.sqrt(np.mean(e[m & ok] ** 2)))

    # measured: wall 0.17 -> 0.027 px (slope 0.4), 0.34 -> 0.032 px (0.8); flat 0.013 px both
    assert rms(first, wall) > 0.1
    assert rms(second, wall) < 0.06
    assert rms(second, wall) < 0.4 * rms(first, wall)
    rep = replaced[0, 0].numpy()
    assert rep[wall].mean() > 0.9
    # the flat road keeps its first match, exactly
    assert not rep[flat].any()
    assert torch.equal(second.shift[0, 0][flat], first.shift[0, 0][flat])


def test_gradient_fit_and_its_significance() -> None:
    rng = np.random.default_rng(3)
    v, u = np.mgrid[0:40, 0:50].astype(np.float64)
    s = 0.3 * u - 0.1 * v + rng.normal(0, 0.05, u.shape)
    s[:, :25] = rng.normal(0, 0.05, (40, 25))  # left half flat noise
    valid = np.ones(u.shape, bool)
    valid[::3, ::2] = False  # holes are left out of the fit
    au, av, z2 = (x[0, 0].numpy() for x in parallax_gradient(_t(s), _t(valid).bool(), 9))
    assert au[20, 40] == pytest.approx(0.3, abs=0.02)
    assert av[20, 40] == pytest.approx(-0.1, abs=0.02)
    assert z2[20, 40] > 100
    # flat noise: a chi-square with 2 degrees of freedom, rarely above 3² (p = 1.1 %)
    assert np.mean(z2[5:-5, 5:20] > 9) < 0.05
    # too few valid pixels: no fit
    sparse = np.zeros(u.shape, bool)
    sparse[::3, ::3] = True
    assert not parallax_gradient(_t(s), _t(sparse).bool(), 9)[2].any()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_gives_the_cpu_result() -> None:
    ref, tgt, s_true = _pair(0.4, 0)
    cfg = DenseHeightConfig()
    out = []
    for dev in ("cpu", "cuda"):
        r, t = ref.to(dev), tgt.to(dev)
        ones = torch.ones_like(r)
        init = _t(cv2.blur(s_true.astype(np.float32), (9, 9))).to(dev)
        first = refine(r, t, ones, ones, torch.zeros_like(r), init, 5, 5, 1.0, ones)
        valid = (first.ncc >= cfg.min_ncc) & (first.last_step <= 0.05 + 0.5 * first.var.sqrt())
        second, rep = slanted_refine(
            r, t, ones, ones, ones, torch.zeros_like(r), first, valid, 5, cfg
        )
        out.append((second.shift[0, 0].cpu().numpy(), rep[0, 0].cpu().numpy()))
    (s_cpu, rep_cpu), (s_gpu, rep_gpu) = out
    assert np.mean(rep_cpu != rep_gpu) < 0.01
    both = rep_cpu & rep_gpu
    assert np.median(np.abs(s_cpu[both] - s_gpu[both])) < 1e-3


def test_plane_fit_residual_marks_steps_not_ramps() -> None:
    """``plane_fit``'s RMS residual: ~0 on a ramp of any slope (a slanted window describes it),
    about half the step on a window centred on a parallax step, 0 where too few pixels are
    valid; ``DenseHeightConfig.step_plane_px`` refuses the step's pixels only."""
    v, u = np.mgrid[0:40, 0:60].astype(np.float64)
    ramp = 0.6 * u - 0.2 * v
    step = np.where(u < 30, 0.0, 3.0)
    valid = torch.ones((1, 1, 40, 60), dtype=torch.bool)
    lim = DenseHeightConfig().step_plane_px
    rms_ramp = plane_fit(_t(ramp), valid, 5)[3][0, 0].numpy()
    assert rms_ramp[5:-5, 5:-5].max() < 1e-2
    rms_step = plane_fit(_t(step), valid, 5)[3][0, 0].numpy()
    # a 5 x 5 window across a step of Δ px: the best plane leaves 0.25-0.28 Δ RMS (measured:
    # 0.73-0.85 px for 3 px), so steps of about 2 px and more are refused
    assert (rms_step[5:-5, 28:32] >= lim).all()
    assert (rms_step[5:-5, 5:25] == 0).all() and (rms_step[5:-5, 35:55] == 0).all()
    none = plane_fit(_t(step), torch.zeros_like(valid), 5)[3]
    assert not none.any()
