"""The dense matcher's CPU shortcuts give the same numbers, bit for bit, as the plain torch
expressions they replace (``matching``: box sums straight into channels with in-place
divisions, the cached window count, the erosion for the window minimum, batched bilinear
samples, the sweep's candidates in batches and the Lucas-Kanade step's reuse of the reference's
window sums while no sample leaves). Seeded synthetic images with a masked edge, so the weights
change between iterations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from roadsurf.reconstruction.dense import matching
from roadsurf.reconstruction.dense.matching import (
    INSIDE_MIN,
    box,
    box_stack,
    gradients,
    inside_weight,
    refine,
    sample,
    sweep,
    window_count,
    window_max,
    window_min,
)

H, W = 37, 53


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(a, dtype=torch.float32)[None, None].contiguous()


@pytest.fixture(scope="module")
def scene() -> dict[str, torch.Tensor]:
    rng = np.random.default_rng(5)
    ref = rng.uniform(20, 230, (H, W))
    tgt = np.roll(ref, 1, axis=1) + rng.normal(0, 2, (H, W))  # ~1 px parallax along x
    m_b = np.ones((H, W))
    m_b[:, -6:] = 0  # image b ends 6 px before the grid's edge
    m_a = np.ones((H, W))
    m_a[:3] = 0
    ang = rng.uniform(-0.2, 0.2, (H, W))
    return {
        "ref": _t(ref),
        "tgt": _t(tgt),
        "mB": _t(m_b),
        "mA": _t(m_a),
        "wx": _t(np.cos(ang)),
        "wy": _t(np.sin(ang)),
        "s0": _t(rng.uniform(0.3, 1.7, (H, W))),
    }


def test_box_stack_is_box_of_the_concatenation_over_the_share(scene) -> None:
    parts = [scene["ref"], scene["tgt"] * scene["mB"], scene["ref"] * scene["tgt"]]
    over = box(scene["mB"], 5).clamp_min(1e-6)
    for win in (3, 5, 7):
        plain = box(torch.cat(parts, 1), win)
        assert torch.equal(box_stack(parts, win), plain)
        assert torch.equal(box_stack(parts, win, over=over), plain / over)


def test_window_count_matches_average_pooling() -> None:
    for win in (1, 3, 5, 7, 9, 13):
        for h, w in ((H, W), (5, 5), (2, 9), (300, 1)):
            ones = torch.ones((1, 1, h, w))
            ref = F.avg_pool2d(ones, win, 1, win // 2, count_include_pad=True) * (win * win)
            assert torch.equal(window_count(h, w, win, torch.device("cpu")), ref)


def test_window_min_is_minus_the_max_of_minus(scene) -> None:
    x = torch.cat([scene["ref"], scene["tgt"]], 1)
    assert torch.equal(window_min(x, 5), -window_max(-x, 5))


def test_sample_batch_is_each_sample(scene) -> None:
    img = torch.cat([scene["tgt"], scene["mB"]], 1)
    xs = torch.arange(W, dtype=torch.float32).expand(H, W)[None, None]
    ys = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)[None, None]
    s = torch.stack([scene["s0"][0], -scene["s0"][0], 0.5 * scene["s0"][0]])  # (3, 1, H, W)
    got = sample(img, xs + s * scene["wx"], ys + s * scene["wy"])
    assert got.shape == (3, 2, H, W)
    for k in range(3):
        one = sample(img, xs + s[k : k + 1] * scene["wx"], ys + s[k : k + 1] * scene["wy"])
        assert torch.equal(got[k : k + 1], one)


def test_sweep_batches_give_the_one_by_one_result(scene, monkeypatch) -> None:
    values = torch.linspace(-0.5, 2.5, 13)

    def shift_of(v: torch.Tensor) -> torch.Tensor:
        return v * (1.0 + 0.1 * scene["wy"])  # any field that broadcasts over the batch

    args = (scene["ref"], scene["tgt"], scene["wx"], scene["wy"], values, shift_of, 5)
    batched = sweep(*args, scene["mB"], scene["mA"])
    plain = sweep(*args)
    monkeypatch.setattr(matching, "SWEEP_BATCH", 1)
    single = sweep(*args, scene["mB"], scene["mA"])
    plain_single = sweep(*args)
    for a, b in ((batched, single), (plain, plain_single)):
        assert torch.equal(a.value, b.value)
        assert torch.equal(a.ncc, b.ncc)
        assert torch.equal(a.interior, b.interior)
    assert batched.interior.float().mean() > 0.5  # the peak is found inside the range


def _refine_plain(ref, tgt, tgt_mask, wx, wy, shift, win, iters, noise_dn, ref_mask):
    """``matching.refine`` as plain torch expressions (before the in-place arithmetic)."""
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij"
    )
    xs, ys = xs[None, None], ys[None, None]
    gx, gy = gradients(tgt)
    stack = torch.cat([tgt, gx * wx + gy * wy, tgt_mask], dim=1)
    r2 = ref * ref
    s = shift.clone()
    last = torch.zeros_like(s)
    wgt = torch.ones_like(s)
    for it in range(iters + 1):
        smp = sample(stack, xs + s * wx, ys + s * wy)
        J, G = smp[:, :1], smp[:, 1:2]
        w_now = inside_weight(smp[:, 2:3], ref_mask)
        wgt = w_now if it == iters else wgt * w_now
        wJ, wG = wgt * J, wgt * G
        m = box(
            torch.cat([wgt, wgt * ref, wgt * r2, wJ, wG, wJ * J, wG * G, wG * ref, wJ * G], 1), win
        )
        share = m[:, :1]
        m = m[:, 1:] / share.clamp_min(1e-6)
        mu_r = m[:, :1]
        var_r = (m[:, 1:2] - mu_r * mu_r).clamp_min(0)
        mu_j, mu_g = m[:, 2:3], m[:, 3:4]
        var_j = (m[:, 4:5] - mu_j * mu_j).clamp_min(1e-6)
        var_g = (m[:, 5:6] - mu_g * mu_g).clamp_min(1e-9)
        cov_rg = m[:, 6:7] - mu_r * mu_g
        cov_jg = m[:, 7:8] - mu_j * mu_g
        g = (var_r / var_j).sqrt().clamp(0.5, 2.0)
        if it == iters:
            break
        ms = box(torch.cat([wgt * s, wG * s, wG * G * s], dim=1), win) / share.clamp_min(1e-6)
        ggs = ms[:, 2:3] - 2 * mu_g * ms[:, 1:2] + mu_g * mu_g * ms[:, :1]
        s_new = ((cov_rg - g * cov_jg) / g + ggs) / var_g
        d = (s_new - s).clamp(-1.0, 1.0)
        last = d.abs()
        s = s + d
    cov_rj = box(wgt * ref * J, win) / share.clamp_min(1e-6) - mu_r * mu_j
    ncc = cov_rj / (var_r.sqrt() * var_j.sqrt() + 1e-3)
    n = share * window_count(H, W, win, torch.device("cpu"))
    res = (2.0 * var_r * (1.0 - ncc)).clamp_min(2.0 * noise_dn * noise_dn)
    var = res / (n.clamp_min(1.0) * g * g * var_g)
    return s, var, ncc, var_g.sqrt(), last, n, wgt > 0.5


def test_refine_is_the_plain_lucas_kanade(scene) -> None:
    args = (scene["ref"], scene["tgt"], scene["mB"], scene["wx"], scene["wy"], scene["s0"])
    for iters in (0, 2, 5):
        got = refine(*args, 5, iters, 1.0, scene["mA"])
        want = _refine_plain(*args, 5, iters, 1.0, scene["mA"])
        fields = (got.shift, got.var, got.ncc, got.grad, got.last_step, got.samples, got.centre)
        for a, b in zip(fields, want, strict=True):
            assert torch.equal(a, b)
    # the masked edge made samples leave while iterating (the weights' shortcut was exercised)
    assert ((scene["mB"] < INSIDE_MIN) & (got.samples > 0)).any()
