"""Photo textures for the road albedo (scikit-image's bundled photographs, no download).

The texture is cut into cells of ``texture_cell_m``; each cell gets its own random rotation,
scale, offset and gain (hashes of the cell index), and neighbouring cells are blended with narrow
smooth transitions, so the photo does not visibly repeat and feature matching does not lock on to
repeats.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from roadsurf.simulation.noise import uniform01

# Per-texture colour tint (R, G, B) and ground size multiplier of one texel.
_TINTS = {
    "gravel": (1.0, 0.97, 0.92),
    "asphalt": (0.93, 0.93, 0.96),
    "brick": (1.05, 0.78, 0.66),
    "grass": (0.78, 0.95, 0.62),
}
_TEXEL_SCALE = {"gravel": 1.0, "asphalt": 0.6, "brick": 3.0, "grass": 1.2}


@lru_cache(maxsize=8)
def _photo(name: str) -> np.ndarray:
    """Greyscale photo as float32 in [0, 1] with its slow illumination gradient removed."""
    import skimage.data as skd

    if name == "asphalt":
        img = skd.gravel()
    elif name in ("gravel", "brick", "grass"):
        img = getattr(skd, name)()
    else:
        raise ValueError(f"unknown texture {name!r}; choose one of {sorted(_TINTS)}")
    a = np.asarray(img, dtype=np.float32) / 255.0
    if a.ndim == 3:
        a = a.mean(axis=2)
    slow = cv2.GaussianBlur(a, (0, 0), 24, borderType=cv2.BORDER_REFLECT)
    a = a / np.maximum(slow, 1e-3) * float(a.mean())
    return np.clip(a, 0.0, 1.0)


@dataclass(frozen=True)
class TextureField:
    """Albedo from a photo texture, evaluable at any ground point."""

    name: str
    texel_m: float  # ground size of one texel of the source photo (m)
    cell_m: float  # cell size of the random transforms (m)
    gsd_m: float  # the resolution it will be sampled at (m); the photo is pre-filtered to it
    seed: int

    @property
    def tint(self) -> tuple[float, float, float]:
        return _TINTS[self.name]

    def _prefiltered(self) -> tuple[np.ndarray, float]:
        return _prefiltered(self.name, self.texel_m * _TEXEL_SCALE[self.name], self.gsd_m)

    def grey(
        self,
        x0: float,
        y_top: float,
        gsd: float,
        rows: int,
        cols: int,
        seed_offset: int = 0,
        scale: float = 1.0,
    ) -> np.ndarray:
        """Texture value (float32 (rows, cols), ~[0, 1]) on the north-up grid whose pixel (r, c)
        centre is (x0 + (c + 0.5) gsd, y_top - (r + 0.5) gsd), local metres.

        Each cell's photo is one affine warp (cv2.warpAffine, wrapping) of its window, weighted
        by a separable partition of unity with narrow smooth transitions between cells."""
        tex, texel = self._prefiltered()
        th, tw = tex.shape
        seed = self.seed * 31 + seed_offset
        cm = self.cell_m
        u = (x0 + (np.arange(cols) + 0.5) * gsd) / cm - 0.5
        v = (y_top - (np.arange(rows) + 0.5) * gsd) / cm - 0.5
        out = np.zeros((rows, cols), np.float32)
        for i in range(int(np.floor(u.min())), int(np.floor(u.max())) + 2):
            wx = _cell_weight(u, i)
            cs = np.nonzero(wx > 0)[0]
            if cs.size == 0:
                continue
            for j in range(int(np.floor(v.min())), int(np.floor(v.max())) + 2):
                wy = _cell_weight(v, j)
                rs = np.nonzero(wy > 0)[0]
                if rs.size == 0:
                    continue
                ang = float(uniform01(i, j, seed + 1)) * 2 * np.pi
                sc = scale * (0.8 + 0.45 * float(uniform01(i, j, seed + 2))) / texel
                ox = float(uniform01(i, j, seed + 3)) * tw
                oy = float(uniform01(i, j, seed + 4)) * th
                gain = 0.9 + 0.2 * float(uniform01(i, j, seed + 5))
                flip = -1.0 if float(uniform01(i, j, seed + 6)) < 0.5 else 1.0
                c_a, c_b, r_a, r_b = int(cs[0]), int(cs[-1]) + 1, int(rs[0]), int(rs[-1]) + 1
                # Offsets from the cell centre ((i + 0.5) cm, (j + 0.5) cm), the rotation pivot.
                dx0 = x0 + (c_a + 0.5) * gsd - (i + 0.5) * cm
                dy0 = y_top - (r_a + 0.5) * gsd - (j + 0.5) * cm
                C, S = np.cos(ang) * sc, np.sin(ang) * sc
                M = np.array(
                    [
                        [C * gsd, S * flip * gsd, (C * dx0 - S * flip * dy0 + ox) % tw],
                        [S * gsd, -C * flip * gsd, (S * dx0 + C * flip * dy0 + oy) % th],
                    ]
                )
                samp = cv2.warpAffine(
                    tex,
                    M,
                    (c_b - c_a, r_b - r_a),
                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_WRAP,
                )
                w = np.outer(wy[r_a:r_b], wx[c_a:c_b]).astype(np.float32)
                out[r_a:r_b, c_a:c_b] += samp * (w * np.float32(gain))
        return out


def _cell_weight(u: np.ndarray, i: int) -> np.ndarray:
    """Weight of cell i at cell coordinates u = x / cell - 0.5 (cell i is centred at u = i):
    a partition of unity with narrow smooth cross-fades at the cell borders."""
    # Blend only within ±BLEND/2 of the cell border, so a cell's window is ~1.3 cells wide.
    f = np.clip((0.5 - np.abs(u - i)) / _BLEND + 0.5, 0.0, 1.0)
    return f * f * (3 - 2 * f)


_BLEND = 0.3  # width of the cross-fade between neighbouring cells (fraction of a cell)


@lru_cache(maxsize=8)
def _prefiltered(name: str, texel_m: float, gsd_m: float) -> tuple[np.ndarray, float]:
    """The photo resampled so one texel is about ``gsd_m`` (area-averaged when shrinking)."""
    a = _photo(name)
    f = texel_m / gsd_m
    if f < 0.95:
        n0 = a.shape[0]
        n = max(16, round(n0 * f))
        a = cv2.resize(a, (n, n), interpolation=cv2.INTER_AREA)
        return a, texel_m * n0 / n
    return a, texel_m
