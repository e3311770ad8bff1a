"""Diverging colour scale for residual heights and its legend (matplotlib, Agg backend)."""

from __future__ import annotations

import io

import numpy as np


def residual_half_range_m(residual_m: np.ndarray, percentile: float, min_range_m: float) -> float:
    """Symmetric colour half-range (m): a robust percentile of |residual|, at least min_range_m."""
    r = np.asarray(residual_m, float)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return float(min_range_m)
    return float(max(min_range_m, np.percentile(np.abs(r), percentile)))


def residual_rgb(residual_m: np.ndarray, half_range_m: float, cmap: str = "RdBu") -> np.ndarray:
    """(N,) residual (m, negative below the road) -> (N, 3) uint8 colours; NaN -> grey."""
    import matplotlib

    cm = matplotlib.colormaps[cmap]
    r = np.asarray(residual_m, float)
    t = np.clip(0.5 + 0.5 * r / half_range_m, 0.0, 1.0)
    rgb = (cm(np.nan_to_num(t, nan=0.5))[..., :3] * 255).astype(np.uint8)
    rgb[~np.isfinite(r)] = (128, 128, 128)
    return rgb


def legend_png(half_range_m: float, cmap: str = "RdBu", label: str = "residual height") -> bytes:
    """A small horizontal colour bar (PNG bytes) labelled in millimetres."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize

    fig, ax = plt.subplots(figsize=(5.0, 0.9), dpi=100)
    fig.subplots_adjust(left=0.05, right=0.95, bottom=0.5, top=0.8)
    mm = 1000.0 * half_range_m
    sm = plt.cm.ScalarMappable(norm=Normalize(-mm, mm), cmap=cmap)
    cb = fig.colorbar(sm, cax=ax, orientation="horizontal")
    cb.set_label(f"{label} (mm; red = below the road)", fontsize=8)
    cb.ax.tick_params(labelsize=8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()
