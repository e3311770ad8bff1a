"""Cracks the 3D tests cannot judge, decided by the images (issue 28).

The pooled 3D test (``crackmap.crack_evidence``) and the raster test read a crack's depth from
the parallax *across* it. Two situations leave them blind, and their "no" then says nothing:

* **Aperture** (``aperture_blind``): the crack runs with the pairs' epipolar direction. Under a
  camera moving forward that is the direction of travel on the road, whatever the tilt (every
  epipolar plane holds the baseline, which lies in the road). The parallax a depth produces
  across the crack is then a small share of the full parallax (``crackaperture``): below
  ``dense_min_across`` the dense readings refuse to measure (LK's aperture), and what the
  sparse points read is their slide along the line.
* **Inconsistent readings** (``readings_disagree``): the pairs' depth readings of the crack
  (each pair's sparse points, each pair's dense reading, with their own standard errors)
  disagree with each other beyond their errors: Cochran's Q = Σ w (x - x̄)² over k readings is
  beyond the chi-square quantile at the level of ``z_k`` (one-sided normal). A common depth
  would give Q ~ χ²(k - 1); a Q far beyond it says the readings do not measure one depth (an
  obliquely seen groove shows one wall, the dark band moves with the viewpoint, a point slides
  along the line), so their pooled mean and z are not evidence either way.

Where the 3D tests are blind, the images decide, as in the dissertation's rule that the image
decides where the 3D is weak: the dark line must have been extracted by the 2D detector in at
least ``image_min_pairs`` pairs at the same place on the map (the candidate's pieces are linked
within ``link_m``), and in at least ``image_min_share`` of the pairs whose image a covers it
(``image_consistent``). Its depth is then not measured: ``max_depth_m`` and ``mean_depth_m``
are NaN and ``measured_on`` is ``"image"``; it is never invented.

A road-level dark line running with the travel is indistinguishable from a crack there by
these sensors; where the readings are consistent and the crack runs across the parallax the
3D test still decides (a road-level line reads z ≈ 0 and is not kept).
"""

from __future__ import annotations

import math

import numpy as np

from roadsurf.detection.config import CrackConfig


def aperture_blind(share: np.ndarray, cfg: CrackConfig) -> bool:
    """True when most of a candidate's pieces (median over its pair pieces) see less than
    ``dense_min_across`` of the depth parallax across the crack (NaN shares: unknown, not
    counted; none known: False)."""
    s = np.asarray(share, float)
    s = s[np.isfinite(s)]
    return bool(len(s) and float(np.median(s)) < cfg.dense_min_across)


def readings_disagree(mean_m: np.ndarray, se_m: np.ndarray, cfg: CrackConfig) -> tuple[bool, float]:
    """(disagree, Q / (k - 1)): whether the k depth readings ``mean_m`` with standard errors
    ``se_m`` ((k,) m; non-positive or non-finite errors are dropped) are inconsistent with one
    common depth: Cochran's Q beyond the χ²(k - 1) quantile at the one-sided normal level of
    ``z_k``. Fewer than 3 readings: (False, nan)."""
    from scipy.stats import chi2, norm

    x = np.asarray(mean_m, float)
    s = np.asarray(se_m, float)
    ok = np.isfinite(x) & np.isfinite(s) & (s > 0)
    x, s = x[ok], s[ok]
    k = len(x)
    if k < 3:
        return False, math.nan
    w = 1.0 / s**2
    xb = float((w * x).sum() / w.sum())
    q = float((w * (x - xb) ** 2).sum())
    level = float(norm.sf(cfg.z_k))
    return bool(q > chi2.isf(level, k - 1)), q / (k - 1)


def image_consistent(n_pairs: int, n_covering: int, cfg: CrackConfig) -> bool:
    """True when the dark line was extracted in at least ``image_min_pairs`` pairs and in at
    least ``image_min_share`` of the ``n_covering`` pairs whose image a covers it."""
    return n_pairs >= cfg.image_min_pairs and n_pairs >= cfg.image_min_share * max(n_covering, 1)
