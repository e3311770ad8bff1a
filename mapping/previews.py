"""PNG previews of the corridor: the downsampled mosaic and the colour-mapped residual surface,
filled tile by tile (bounded size) and cropped to the observed data when written."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from roadsurf.core.atomic import atomic_path
from roadsurf.io import runfolder as rf
from roadsurf.io.formats import GridSpec
from roadsurf.mapping.raster import TileLattice


class Previews:
    """Downsampled mosaic and colour-mapped surface over the whole corridor (bounded size)."""

    def __init__(self, fg: GridSpec, max_px: int) -> None:
        self.f = max(1, int(math.ceil(max(fg.width, fg.height) / max_px)))
        self.h = max(1, fg.height // self.f)
        self.w = max(1, fg.width // self.f)
        self.mos = np.zeros((self.h, self.w, 3), np.uint8)
        self.res = np.full((self.h, self.w), np.nan, np.float32)

    def add(
        self, t: tuple[int, int], lat: TileLattice, res_t: np.ndarray, mos_t: np.ndarray
    ) -> None:
        tp, f = lat.tile_px, self.f
        # exact integer bounds so neighbouring tiles meet without a gap
        r0, c0 = t[0] * tp // f, t[1] * tp // f
        sh, sw = (t[0] + 1) * tp // f - r0, (t[1] + 1) * tp // f - c0
        hh, ww = min(sh, self.h - r0), min(sw, self.w - c0)
        if hh <= 0 or ww <= 0:
            return
        m = cv2.resize(mos_t, (sw, sh), interpolation=cv2.INTER_AREA)
        valid = np.isfinite(res_t).astype(np.float32)
        num = cv2.resize(np.nan_to_num(res_t), (sw, sh), interpolation=cv2.INTER_AREA)
        den = cv2.resize(valid, (sw, sh), interpolation=cv2.INTER_AREA)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(den > 0.25, num / den, np.nan)
        mm = m[:hh, :ww]
        has = mm.any(axis=2)
        self.mos[r0 : r0 + hh, c0 : c0 + ww][has] = mm[has]
        rr = r[:hh, :ww]
        fin = np.isfinite(rr)
        self.res[r0 : r0 + hh, c0 : c0 + ww][fin] = rr[fin]

    def observed_box(self, margin: int = 4) -> tuple[slice, slice]:
        """Rows and columns of the previews that hold data (mosaic or surface), with a margin:
        the corridor's grid can be far larger than what a short drive saw."""
        has = self.mos.any(axis=2) | np.isfinite(self.res)
        if not has.any():
            return slice(0, self.h), slice(0, self.w)
        rows, cols = np.flatnonzero(has.any(axis=1)), np.flatnonzero(has.any(axis=0))
        return (
            slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, self.h)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, self.w)),
        )

    def write(self, run_dir: Path) -> None:
        """Both PNGs, cropped to the observed data (``observed_box``)."""
        from matplotlib import colormaps

        box = self.observed_box()
        mos, res = self.mos[box], self.res[box]
        with atomic_path(run_dir / rf.MOSAIC_PREVIEW) as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(mos, cv2.COLOR_RGB2BGR))
        fin = np.isfinite(res)
        lim = 0.005
        if fin.any():
            lim = max(lim, float(np.percentile(np.abs(res[fin]), 99.5)))
        rgba = colormaps["RdBu"](np.clip(np.nan_to_num(res) / (2 * lim) + 0.5, 0, 1))
        img = (rgba[..., :3] * 255).astype(np.uint8)
        img[~fin] = 235
        mm = lim * 1000
        pad = np.full((28, img.shape[1], 3), 255, np.uint8)
        # the longest legend that fits the image's width (a two-frame drive's crop is narrow)
        for label, scale in (
            (f"residual height: red {-mm:.0f} mm (below) .. blue +{mm:.0f} mm", 0.5),
            (f"height: red {-mm:.0f} .. blue +{mm:.0f} mm", 0.45),
            (f"red {-mm:.0f} .. blue +{mm:.0f} mm", 0.4),
        ):
            (tw, _), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
            if tw <= img.shape[1] - 8:
                break
        cv2.putText(pad, label, (4, 19), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
        out = np.vstack([img, pad]) if tw <= img.shape[1] - 8 else img
        with atomic_path(run_dir / rf.SURFACE_PREVIEW) as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(out, cv2.COLOR_RGB2BGR))
