"""Deterministic procedural noise that can be evaluated at any point of the plane.

The world must look the same whichever tile or chunk asks for it (frames render local patches,
ground truth is written block by block), so random fields are hashes of integer lattice
coordinates, never draws from a stateful generator.
"""

from __future__ import annotations

import cv2
import numpy as np

_M1 = np.uint64(0x9E3779B97F4A7C15)
_M2 = np.uint64(0xC2B2AE3D27D4EB4F)
_M3 = np.uint64(0x165667B19E3779F9)
_F1 = np.uint64(0xBF58476D1CE4E5B9)
_F2 = np.uint64(0x94D049BB133111EB)


def hash_u64(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """splitmix64-style hash of integer lattice coordinates (any int arrays, broadcast) -> uint64."""
    a = np.asarray(ix, dtype=np.int64).astype(np.uint64)
    b = np.asarray(iy, dtype=np.int64).astype(np.uint64)
    s = np.uint64(seed & 0xFFFFFFFFFFFFFFFF)
    with np.errstate(over="ignore"):
        h = a * _M1 ^ (b + np.uint64(0x632BE59BD9B4E019)) * _M2 ^ (s + np.uint64(1)) * _M3
        h ^= h >> np.uint64(30)
        h *= _F1
        h ^= h >> np.uint64(27)
        h *= _F2
        h ^= h >> np.uint64(31)
    return h


def uniform01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Hash -> uniform float64 in [0, 1)."""
    return (hash_u64(ix, iy, seed) >> np.uint64(11)).astype(np.float64) * (1.0 / 2.0**53)


def _knot_table(i0: int, j0: int, ni: int, nj: int, seed: int) -> np.ndarray:
    """(nj, ni) float32 lattice values (zero mean, unit variance, uniform) for knots i0.., j0.."""
    jj, ii = np.mgrid[j0 : j0 + nj, i0 : i0 + ni]
    return ((uniform01(ii, jj, seed) - 0.5) * (2.0 * np.sqrt(3.0))).astype(np.float32)


def _lattice_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Bicubic interpolation of hashed lattice values at lattice coordinates u, v."""
    shape = np.shape(u)
    u = np.asarray(u, np.float64).ravel()
    v = np.asarray(v, np.float64).ravel()
    if u.size == 0:
        return np.zeros(shape, np.float32)
    i0, j0 = int(np.floor(u.min())) - 1, int(np.floor(v.min())) - 1
    ni, nj = int(np.floor(u.max())) - i0 + 3, int(np.floor(v.max())) - j0 + 3
    if ni * nj > 16_000_000:
        raise ValueError(
            "value_noise: points too spread out for one lattice table; evaluate in chunks"
        )
    table = _knot_table(i0, j0, ni, nj, seed)
    # cv2.remap wants 2-D maps shorter than 32767 per side: fold the points into rows.
    n = u.size
    w = 4096 if n > 4096 else n
    rows = -(-n // w)
    pad = rows * w - n
    mu = np.pad((u - i0).astype(np.float32), (0, pad)).reshape(rows, w)
    mv = np.pad((v - j0).astype(np.float32), (0, pad)).reshape(rows, w)
    out = cv2.remap(table, mu, mv, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n].reshape(shape)


def value_noise(x: np.ndarray, y: np.ndarray, spacing_m: float, seed: int) -> np.ndarray:
    """Smooth value noise (bicubic over a hashed lattice of spacing ``spacing_m``); zero mean,
    unit std. x, y: arrays of equal shape in metres. Returns float32 of the same shape."""
    u = np.asarray(x, dtype=np.float64) / spacing_m
    v = np.asarray(y, dtype=np.float64) / spacing_m
    return _lattice_noise(u, v, seed) * np.float32(1.0 / _value_noise_std())


def _value_noise_std() -> float:
    """Std of the bicubically interpolated unit-variance lattice. Measured once with
    ``np.std(_lattice_noise(u, v, 12345))`` on the grid u, v = meshgrid(arange(0, 300, 0.137));
    a constant, so that output bytes never depend on a re-measurement (tests check std ~ 1)."""
    return 0.8577688932418823


def fractal_noise(
    x: np.ndarray,
    y: np.ndarray,
    spacings_m: tuple[float, ...],
    weights: tuple[float, ...],
    seed: int,
) -> np.ndarray:
    """Sum of value-noise octaves, normalised to unit std (octaves are independent)."""
    w = np.asarray(weights, dtype=np.float64)
    w = w / np.sqrt(np.sum(w**2))
    out = np.zeros(np.shape(x), dtype=np.float32)
    for k, (sp, wk) in enumerate(zip(spacings_m, w, strict=True)):
        out += np.float32(wk) * value_noise(x, y, sp, seed * 7919 + k * 104729 + 1)
    return out
