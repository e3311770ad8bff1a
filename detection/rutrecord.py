"""The record of a traced rut (``RutTrace``) and what is read off it alone: the longest stretch
no flat gap cuts (two potholes in a line are not a rut), and the union of two traces of one rut.

Kept apart from the tracing so that a map region (``mapseg.Region.rut``) can name its type.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from roadsurf.detection.config import RutConfig


@dataclass
class RutTrace:
    """A traced rut: stations along its centre line and its cells on the full grid."""

    centres_xy_m: np.ndarray  # (S, 2) station centres (grid easting, northing, m)
    depth_m: np.ndarray  # (S,) station depth below the straightedge line (m)
    width_m: np.ndarray  # (S,) trough width at depth 0, extrapolated (m)
    noise_m: np.ndarray  # (S,) σ of the station's levelled profile on the road (m)
    in_rut: np.ndarray  # (S,) bool
    length_m: float  # along the centre line, first to last station in the rut, plus ends (m)
    max_depth_m: float  # largest running median of the stations' depths (m)
    # length added beyond the first and the last station in the rut: the rut's depth ramp
    # extrapolated to depth 0, like its width (m)
    end_extension_m: tuple[float, float] = (0.0, 0.0)
    rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) cells
    cols: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    cell_profile_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K,) depth (m)

    @property
    def measured_length_m(self) -> float:
        """Length of the stations in the rut, without the extrapolated ends (m)."""
        return self.length_m - sum(self.end_extension_m)

    @property
    def body_width_m(self) -> float:
        """Median trough width of the stations at least half as deep as the rut (m): the
        tapered ends read narrow, because the rim threshold cuts a shallow trough higher up."""
        sel = self.in_rut & (self.depth_m >= 0.5 * self.max_depth_m)
        if not sel.any():
            sel = self.in_rut
        return float(np.median(self.width_m[sel])) if sel.any() else float("nan")


def longest_trough_m(trace: RutTrace, cfg: RutConfig) -> float:
    """Length (m) of the trace's longest stretch that no flat gap cuts.

    A station is at road level when it lies shallower than ``flat_gap_frac`` x the trough on
    both sides of it (the deepest station within ``flat_gap_ref_m`` before it, and after it);
    at least ``flat_gap_m`` of such stations in a row are flat road between two troughs. A
    rut shallows and deepens along its length and noise drops single stations out of it, but
    it does not come back to the road level between two deep stretches; two potholes in a
    line do. A stretch runs from its first station in the rut to its last. Without flat gaps
    this is ``measured_length_m``."""
    ok = np.asarray(trace.in_rut, bool)
    if not ok.any():
        return 0.0
    c = np.asarray(trace.centres_xy_m, float)
    depth = np.where(np.isfinite(trace.depth_m), trace.depth_m, 0.0)
    n = depth.size
    w = max(1, int(round(cfg.flat_gap_ref_m / cfg.step_m)))
    pad = np.r_[np.full(w, -np.inf), depth, np.full(w, -np.inf)]
    win = np.lib.stride_tricks.sliding_window_view(pad, w)  # win[j] = pad[j : j + w]
    before = win[:n].max(axis=1)  # depth[k - w : k]
    after = win[w + 1 : w + 1 + n].max(axis=1)  # depth[k + 1 : k + 1 + w]
    with np.errstate(invalid="ignore"):  # 0 x -inf at the ends (flat_gap_frac 0): not flat
        flat = depth < cfg.flat_gap_frac * np.minimum(before, after)
    min_run = max(1, int(round(cfg.flat_gap_m / cfg.step_m)))
    # runs of flat stations at least min_run long cut the trace into stretches
    runs, n_runs = ndimage.label(flat)
    long_runs = 1 + np.flatnonzero(np.bincount(runs, minlength=n_runs + 1)[1:] >= min_run)
    stretches, n_stretches = ndimage.label(~np.isin(runs, long_runs))
    seg = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))]
    best = 0.0
    for s in range(1, n_stretches + 1):
        idx = np.flatnonzero((stretches == s) & ok)
        if idx.size:
            best = max(best, float(seg[idx[-1]] - seg[idx[0]]) + cfg.step_m)
    return best


def union_traces(a: RutTrace, b: RutTrace, width: int) -> RutTrace:
    """Two traces of one rut: the stations of ``a`` (the longer, see ``trace_ruts``), both
    traces' cells."""
    key_a = a.rows.astype(np.int64) * width + a.cols
    key_b = b.rows.astype(np.int64) * width + b.cols
    extra = ~np.isin(key_b, key_a)
    return dataclasses.replace(
        a,
        max_depth_m=max(a.max_depth_m, b.max_depth_m),
        rows=np.concatenate([a.rows, b.rows[extra]]),
        cols=np.concatenate([a.cols, b.cols[extra]]),
        cell_profile_m=np.concatenate([a.cell_profile_m, b.cell_profile_m[extra]]),
    )
