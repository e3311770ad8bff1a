"""The shifted-window pass of the dense match (reconstruction.dense.shifted) on a seeded synthetic
pair with a parallax step: a road at parallax 0 left of column U0 and a surface 3 px away right
of it (a pothole's floor seen past its rim), the target image rendered from the reference
texture through that field, with fresh texture where the step uncovers the target."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from roadsurf.reconstruction.dense.checks import REJECT_LR, REJECT_NCC, REJECT_STEP
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.matching import refine, sample
from roadsurf.reconstruction.dense.shifted import shifted_refine

H, W = 80, 120
U0 = 60  # the step's column (px)
STEP = 3.0  # parallax right of the step (px)
SS = 8  # texture supersampling


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float32)[None, None]


def _texture(rng: np.random.Generator) -> np.ndarray:
    big = np.zeros((H * SS, (W + 20) * SS), np.float32)
    for sig, amp in ((1.0, 1.0), (2.0, 1.0), (4.0, 0.6)):
        n = rng.standard_normal(big.shape).astype(np.float32)
        big += amp * cv2.GaussianBlur(n, (0, 0), sig * SS)
    return 128 + 40 * big / big.std()


def _pair(seed: int) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    rng = np.random.default_rng(seed)
    big, fresh = _texture(rng), _texture(rng)

    def tex(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        mu = ((u + 0.5) * SS - 0.5).astype(np.float32)
        mv = ((v + 0.5) * SS - 0.5).astype(np.float32)
        return cv2.remap(img, mu, mv, cv2.INTER_LINEAR)

    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    s_true = np.where(u < U0, 0.0, STEP)
    # target column u shows reference column u (left), u - STEP (right of U0 + STEP), and
    # texture the reference never saw between
    tgt = np.where(
        u < U0, tex(big, u, v), np.where(u >= U0 + STEP, tex(big, u - STEP, v), tex(fresh, u, v))
    )
    tgt = tgt + rng.normal(0, 1.0, (H, W)).astype(np.float32)
    return _t(tex(big, u, v)), _t(tgt.astype(np.float32)), s_true


def test_shifted_windows_cut_the_fattening_at_a_step() -> None:
    cfg = DenseHeightConfig(device="cpu")
    errs_first, errs_second, flat_same = [], [], []
    for seed in (0, 1):
        ref, tgt, s_true = _pair(seed)
        ones = torch.ones_like(ref)
        wx, wy = ones, torch.zeros_like(ref)
        init = _t(cv2.blur(s_true.astype(np.float32), (9, 9)))  # a blurred start, the sweep's
        first = refine(ref, tgt, ones, wx, wy, init, 5, 5, 1.0, ones)
        tol = (0.5 * first.var.sqrt()).clamp_min(0.05)
        flags = (first.ncc < cfg.min_ncc).to(torch.uint8) * REJECT_NCC
        flags |= (first.last_step > tol).to(torch.uint8) * REJECT_STEP
        # the left-right check, as dense.parallax runs it
        rev = refine(tgt, ref, ones, wx, wy, -init, 5, 2, 1.0, ones)
        ys, xs = torch.meshgrid(
            torch.arange(H, dtype=torch.float32),
            torch.arange(W, dtype=torch.float32),
            indexing="ij",
        )
        back = sample(
            rev.shift, xs[None, None] + first.shift, ys[None, None].expand_as(first.shift)
        )
        flags |= ((first.shift + back).abs() > cfg.lr_max_px).to(torch.uint8) * REJECT_LR
        second, rep = shifted_refine(ref, tgt, ones, ones, wx, wy, first, flags, 5, cfg)
        ok = (flags == 0)[0, 0].numpy()
        # within a window of the step, less the pixel on each side of it: a 3 x 3 neighbourhood
        # there holds both sides (measured 1.1-1.9 px off before and after; the plane test,
        # DenseHeightConfig.step_plane_px, refuses them)
        band = np.zeros((H, W), bool)
        band[6:-6, U0 - 4 : U0 + 4] = True
        band[:, U0 - 1 : U0 + 1] = False
        e1 = first.shift[0, 0].numpy() - s_true
        e2 = second.shift[0, 0].numpy() - s_true
        errs_first.append(e1[band & ok])
        errs_second.append(e2[band & ok])
        flat = np.zeros((H, W), bool)
        flat[6:-6, 10:40] = True
        flat_same.append(not rep[0, 0].numpy()[flat].any())
        assert torch.equal(second.shift[0, 0][flat], first.shift[0, 0][flat])
    r1 = float(np.sqrt(np.mean(np.concatenate(errs_first) ** 2)))
    r2 = float(np.sqrt(np.mean(np.concatenate(errs_second) ** 2)))
    # measured: 0.47 -> 0.04 px (seeds 0 and 1)
    assert r1 > 0.3
    assert r2 < 0.1
    assert all(flat_same)
