"""Seam samples of the dense surface: where two pairs both measured a cell, each pair's own
levelled height there (the sample ``DenseSurface`` fuses), kept on a sub-grid of cells and
written to ``dense_seams.npz`` for the seam step of ``roadsurf evaluate``
(``evaluation.seams.seam_report``).

The sparse map's seam step compares a few hundred feature points per overlap, and each seam's
median then has a standard error of 0.2-0.4 mm, at the size of the seams it should rank. The
dense surface measures every cell of an overlap: thousands of samples per seam. Neighbouring
cells share a matching window (``dense.window_px`` work-grid px over ``dense_gsd_px`` px per
cell), so only cells a window apart are kept (``seam_stride_cells``): their errors are partly
independent, the rest would add samples, not information.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np

from roadsurf.core.atomic import write_npz_atomic
from roadsurf.io.formats import GridSpec
from roadsurf.io.runfolder import DENSE_SEAMS

__all__ = ["DENSE_SEAMS", "SeamSamples", "seam_stride_cells"]


def seam_stride_cells(window_px: int, cell_px: float) -> int:
    """Cells between kept samples (>= 1): one matching window (``window_px`` work-grid px)
    over the cell's size (``cell_px`` work-grid px per cell), rounded up."""
    if cell_px <= 0:
        return 1
    return max(1, math.ceil(window_px / cell_px))


class SeamSamples:
    """Collects, tile by tile, the samples of cells that two or more pairs measured (on every
    ``stride``-th row and column of the full grid); thread-safe."""

    def __init__(self, grid: GridSpec, stride: int) -> None:
        self.grid, self.stride = grid, max(1, int(stride))
        self._lock = threading.Lock()
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def add(
        self,
        row0: int,
        col0: int,
        width: int,
        samples: list[tuple[int, np.ndarray, np.ndarray]],
    ) -> None:
        """One tile's samples: (pair's frame-a index, cell index in the tile (row * width +
        col), levelled height (m)) per pair; the tile's top-left cell is (row0, col0) of the
        full grid."""
        if len(samples) < 2:
            return
        fr = np.concatenate([np.full(len(c), f, np.int32) for f, c, _ in samples])
        cell = np.concatenate([c for _, c, _ in samples]).astype(np.int64)
        val = np.concatenate([v for _, _, v in samples]).astype(np.float32)
        rows = cell // width + row0
        cols = cell % width + col0
        keep = (rows % self.stride == 0) & (cols % self.stride == 0) & np.isfinite(val)
        if not keep.any():
            return
        fr, cell, val, rows, cols = fr[keep], cell[keep], val[keep], rows[keep], cols[keep]
        _, inv, cnt = np.unique(cell, return_inverse=True, return_counts=True)
        two = cnt[inv] >= 2  # seen by two or more pairs
        if not two.any():
            return
        part = (rows[two].astype(np.int32), cols[two].astype(np.int32), fr[two], val[two])
        with self._lock:
            self._parts.append(part)

    @property
    def n(self) -> int:
        return sum(len(p[0]) for p in self._parts)

    def write(self, path: Path) -> Path:
        """``path`` (npz): row, col (int32, full grid), frame_index (int32, the pair's frame a),
        residual_m (float32), and the grid (crs, x0_m, y0_m, gsd_m) and stride."""
        with self._lock:
            parts = list(self._parts)
        cols_ = [np.concatenate([p[i] for p in parts]) if parts else np.zeros(0) for i in range(4)]
        g = self.grid
        write_npz_atomic(
            path,
            row=cols_[0].astype(np.int32),
            col=cols_[1].astype(np.int32),
            frame_index=cols_[2].astype(np.int32),
            residual_m=cols_[3].astype(np.float32),
            crs=np.array(g.crs),
            x0_m=np.float64(g.x0_m),
            y0_m=np.float64(g.y0_m),
            gsd_m=np.float64(g.gsd_m),
            stride=np.int32(self.stride),
        )
        return path
