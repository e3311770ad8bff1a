"""The crack detector's oriented filter bank: the maximum over kernels of ``cv2.filter2D``,
bit for bit, with each image tile transformed once for the whole bank.

``cv2.filter2D`` correlates a float32 image with a kernel of ``DFT_MIN_TAPS`` taps or more
through the DFT (OpenCV's ``crossCorr``): the image is cut into tiles; each tile, with the
kernel's reach of border around it, is zero-padded to an optimal DFT size, transformed in
float64, multiplied by the conjugate spectrum of the kernel, transformed back and rounded to
float32. For a bank of kernels of one size (``crackfilter.line_response``: 24 directions of a
33 px segment) it transforms the same tiles once per kernel. ``bank_max`` repeats the same
steps with the same OpenCV calls, but transforms each tile once and each kernel once per
process, which takes about 40 % less time.

Equality is checked, not assumed: once per image size, kernel size and border, the replica is
compared with ``cv2.filter2D`` on a seeded random image (every tile and border); where the two
differ in any bit (another OpenCV build or version), plain ``cv2.filter2D`` is used.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence

import cv2
import numpy as np

# Fewest kernel taps for which filter2D takes its DFT path (float32 in and out with SSE3;
# OpenCV's dftFilter2D). Smaller kernels are filtered directly, as filter2D does.
DFT_MIN_TAPS = 130
_BLOCK_SCALE, _MIN_BLOCK = 4.5, 256  # OpenCV crossCorr's tile size: 4.5 kernels, >= 256 - k

_lock = threading.Lock()
_verified: dict[tuple[int, int, int, int, int], bool] = {}
_spectra: OrderedDict[bytes, list[np.ndarray]] = OrderedDict()


def bank_max(img: np.ndarray, kernels: Sequence[np.ndarray], border: int) -> np.ndarray:
    """Max over ``kernels`` of ``cv2.filter2D(img, -1, k, borderType=border)``: (H, W) float32.

    img: (H, W) float32; kernels: (kh, kw) float32 of one size, anchored at their centre.
    """
    if not len(kernels):
        raise ValueError("bank_max: the filter bank holds no kernel")
    img = np.asarray(img, np.float32)
    kh, kw = kernels[0].shape
    if (
        img.ndim != 2
        or kh * kw < DFT_MIN_TAPS
        or any(k.shape != (kh, kw) for k in kernels)
        or not _replica_ok(img.shape, kernels[0], border)
    ):
        c = cv2.filter2D(img, -1, kernels[0], borderType=border)
        for k in kernels[1:]:
            c = np.maximum(c, cv2.filter2D(img, -1, k, borderType=border))
        return c
    return _bank_max(img, kernels, border)


def _plan(h: int, w: int, kh: int, kw: int) -> tuple[int, int, int, int]:
    """crossCorr's tile (block) size and DFT size: (bw, bh, dw, dh) px."""
    bw = min(max(round(kw * _BLOCK_SCALE), _MIN_BLOCK - kw + 1), w)  # round: cvRound, half even
    bh = min(max(round(kh * _BLOCK_SCALE), _MIN_BLOCK - kh + 1), h)
    dw = max(cv2.getOptimalDFTSize(bw + kw - 1), 2)
    dh = cv2.getOptimalDFTSize(bh + kh - 1)
    return min(dw - kw + 1, w), min(dh - kh + 1, h), dw, dh


def _tiles(
    img: np.ndarray, kh: int, kw: int, border: int
) -> tuple[list[tuple[int, int, int, int, np.ndarray]], int, int]:
    """The spectra of the image's tiles as crossCorr makes them: ([(x, y, bw, bh, spectrum)],
    dh, dw)."""
    h, w = img.shape
    bw, bh, dw, dh = _plan(h, w, kh, kw)
    ax, ay = kw // 2, kh // 2
    out = []
    for y in range(0, h, bh):
        for x in range(0, w, bw):
            sw, sh = min(bw, w - x), min(bh, h - y)
            dsw, dsh = sw + kw - 1, sh + kh - 1
            x0, y0 = x - ax, y - ay
            x1, y1 = max(0, x0), max(0, y0)
            x2, y2 = min(w, x0 + dsw), min(h, y0 + dsh)
            src: np.ndarray = img[y1:y2, x1:x2].astype(np.float64)
            if x2 - x1 < dsw or y2 - y1 < dsh:
                src = cv2.copyMakeBorder(
                    src, y1 - y0, dsh - (y2 - y1) - (y1 - y0), x1 - x0,
                    dsw - (x2 - x1) - (x1 - x0), border | cv2.BORDER_ISOLATED,
                )  # fmt: skip
            buf = np.zeros((dh, dw), np.float64)
            buf[:dsh, :dsw] = src
            out.append((x, y, sw, sh, cv2.dft(buf, flags=0, nonzeroRows=dsh)))
    return out, dh, dw


def _kernel_spectra(kernels: Sequence[np.ndarray], dh: int, dw: int) -> list[np.ndarray]:
    """The kernels' spectra at DFT size (dh, dw), kept for the process (a few banks)."""
    key = b"".join(
        [np.array([dh, dw]).tobytes()] + [np.asarray(k, np.float32).tobytes() for k in kernels]
    )
    with _lock:
        got = _spectra.get(key)
        if got is not None:
            _spectra.move_to_end(key)
            return got
    spectra = []
    for k in kernels:
        buf = np.zeros((dh, dw), np.float64)
        buf[: k.shape[0], : k.shape[1]] = k
        spectra.append(cv2.dft(buf, flags=0, nonzeroRows=k.shape[0]))
    with _lock:
        _spectra[key] = spectra
        while len(_spectra) > 4:
            _spectra.popitem(last=False)
    return spectra


def _bank_max(img: np.ndarray, kernels: Sequence[np.ndarray], border: int) -> np.ndarray:
    """``bank_max`` through the shared tile spectra (no checks)."""
    kh, kw = kernels[0].shape
    tiles, dh, dw = _tiles(img, kh, kw, border)
    c = np.empty(img.shape, np.float32)
    x = np.empty(img.shape, np.float32)
    for i, K in enumerate(_kernel_spectra(kernels, dh, dw)):
        for x0, y0, sw, sh, F in tiles:
            r = cv2.dft(
                cv2.mulSpectrums(F, K, 0, conjB=True),
                flags=cv2.DFT_INVERSE | cv2.DFT_SCALE,
                nonzeroRows=sh,
            )
            x[y0 : y0 + sh, x0 : x0 + sw] = r[:sh, :sw]  # float64 -> float32, as crossCorr
        if i == 0:
            c[:] = x
        else:
            np.maximum(c, x, out=c)
    return c


def _replica_ok(shape: tuple[int, ...], kernel: np.ndarray, border: int) -> bool:
    """Whether ``_bank_max`` equals ``cv2.filter2D`` bit for bit at this image size, kernel size
    and border (checked once, on a seeded random image)."""
    h, w = int(shape[0]), int(shape[1])
    kh, kw = kernel.shape
    key = (h, w, kh, kw, int(border))
    with _lock:
        ok = _verified.get(key)
    if ok is None:
        img = np.random.default_rng(0).random((h, w), dtype=np.float32)
        k = np.asarray(kernel, np.float32)
        ok = bool(
            np.array_equal(
                _bank_max(img, [k], border).view(np.uint32),
                cv2.filter2D(img, -1, k, borderType=border).view(np.uint32),
            )
        )
        with _lock:
            _verified[key] = ok
    return ok
