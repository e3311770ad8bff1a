"""mapping.previews: the PNGs are cropped to the observed data (a short drive on a large
corridor grid showed a tiny patch in a wide empty canvas)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from roadsurf.io import runfolder as rf
from roadsurf.mapping.previews import Previews
from roadsurf.mapping.raster import TileLattice


def test_previews_crop_to_the_observed_tile(tmp_path: Path) -> None:
    lat = TileLattice("EPSG:32617", 0.0, 0.0, 0.005, 256, n_rows=8, n_cols=8)
    prev = Previews(lat.full_grid, max_px=512)  # 2048 px grid -> factor 4, 512 x 512 canvas
    res = np.full((256, 256), np.nan, np.float32)
    res[50:150, 60:200] = -0.01
    mos = np.zeros((256, 256, 3), np.uint8)
    mos[40:160, 50:210] = 120
    prev.add((3, 5), lat, res, mos)
    prev.write(tmp_path)
    m = cv2.imread(str(tmp_path / rf.MOSAIC_PREVIEW))
    s = cv2.imread(str(tmp_path / rf.SURFACE_PREVIEW))
    # the data is 120 x 160 grid px = 30 x 40 preview px; plus a 4 px margin each side
    # (area resampling may add one partly covered preview pixel on a side)
    assert 38 <= m.shape[0] <= 40 and 48 <= m.shape[1] <= 50, m.shape
    assert m[5:-5, 5:-5].min() > 0 and m[:2].max() == 0
    assert s.shape[1] == m.shape[1] and m.shape[0] <= s.shape[0] <= m.shape[0] + 28
    empty = Previews(lat.full_grid, max_px=512)  # nothing observed: the whole canvas
    empty.write(tmp_path)
    assert cv2.imread(str(tmp_path / rf.MOSAIC_PREVIEW)).shape[:2] == (512, 512)


def test_surface_legend_fits_a_narrow_preview(tmp_path: Path) -> None:
    """A 240 px wide preview keeps its whole legend (the long one was cut at the right edge)."""
    lat = TileLattice("EPSG:32617", 0.0, 0.0, 0.005, 256, n_rows=1, n_cols=1)
    prev = Previews(lat.full_grid, max_px=512)
    res = np.full((256, 256), np.nan, np.float32)
    res[:, 8:240] = np.linspace(-0.05, 0.05, 232, dtype=np.float32)
    prev.add((0, 0), lat, res, np.full((256, 256, 3), 90, np.uint8))
    prev.write(tmp_path)
    s = cv2.imread(str(tmp_path / rf.SURFACE_PREVIEW))
    m = cv2.imread(str(tmp_path / rf.MOSAIC_PREVIEW))
    assert s.shape[0] == m.shape[0] + 28  # the legend strip is there
    strip = s[-28:]
    assert strip.min() < 128  # text drawn
    assert strip[:, -3:].min() == 255  # and none of it reaches the right edge
