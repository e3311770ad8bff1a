"""The band next to the overlap's edge that the sweep could not score starts from its swept
neighbours (``matching.fill_unswept``)."""

from __future__ import annotations

import torch

from roadsurf.reconstruction.dense.matching import fill_unswept


def test_unswept_band_takes_its_swept_neighbours() -> None:
    g = torch.Generator().manual_seed(3)
    h, w = 20, 30
    # a smooth height ramp (m); the sweep scored none of the right-hand 4 columns
    ramp = torch.linspace(-0.01, 0.01, w).repeat(h, 1)[None, None]
    value = ramp + 1e-4 * torch.randn(1, 1, h, w, generator=g)
    ncc = torch.full((1, 1, h, w), 0.9)
    ncc[..., -4:] = -2.0
    value[..., -4:] = -0.12  # the sweep's first candidate, the deepest height
    out = fill_unswept(value, ncc, steps=5)
    # swept pixels are untouched; the band continues the last swept columns (within 1 mm)
    assert torch.equal(out[..., :-4], value[..., :-4])
    edge = value[..., -5].mean()
    assert (out[..., -4:] - edge).abs().max() < 1e-3


def test_steps_bound_the_reach() -> None:
    value = torch.zeros(1, 1, 5, 12)
    ncc = torch.full((1, 1, 5, 12), -2.0)
    ncc[..., :2] = 0.8
    value[..., 2:] = -0.12
    out = fill_unswept(value, ncc, steps=3)
    # 3 steps reach 3 columns past the swept ones; beyond, the value stays as swept
    assert torch.equal(out[..., 2:5], torch.zeros(1, 1, 5, 3))
    assert torch.equal(out[..., 5:], value[..., 5:])
    # nothing unswept: nothing changes
    assert torch.equal(fill_unswept(value, torch.ones_like(ncc), steps=3), value)
