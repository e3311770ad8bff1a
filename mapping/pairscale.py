"""Pairs whose metric scale disagrees with the trajectory, rescaled to it.

A pair's scale is α = h / d_c (the camera height over the distance to the plane fitted to its
points). When a pothole fills most of the view (a nadir camera 1.1 m high sees 1.2 × 0.9 m of
road), the plane is fitted through the bowl, d_c is too long and every point of the pair sits
too near the camera: a 1.5 m pothole 48 mm deep read its pairs 1.3 % and 2.9 % short, their
points 13-18 mm high, and the fused floor 19 mm shallow (simulated, RTK). The trajectory does not
share the error: GPS and the neighbouring pairs fix each frame, so its baseline between the
pair's frames is within 0.1-0.2 % of the drive's typical ratio to the pairs' own.

``rescaled_pairs`` compares every ok pair's baseline |t| with the trajectory's, and rescales a
pair whose ratio departs from the drive's median ratio by more than ``max(MIN_DEPARTURE,
K_SIGMA × robust σ)`` and at most ``MAX_DEPARTURE``: its translation, points, plane offset, plane distances and covariances
scale together (R, H and F do not depend on the scale). Only with GPS: without it the
trajectory's baselines are the pairs' own. Pure function of the pairs and the trajectory.
"""

from __future__ import annotations

import copy
import logging
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.fits import robust_sigma
from roadsurf.mapping.types import Trajectory

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

MIN_DEPARTURE = 0.01  # a ratio within 1 % of the drive's median is left alone (-)
K_SIGMA = 4.0  # ... and within this many robust σ of the ratios (-)
MIN_PAIRS = 5  # fewer ok pairs: no median to compare with
# a pair further off than this is not a plane tilted by a defect (1-5 %) but a trajectory that
# rests on something else there (a GPS-bridged gap, a scale the fixes disagree with): left alone
MAX_DEPARTURE = 0.10


def scale_ratios(pairs: list[PairResult], traj: Trajectory) -> np.ndarray:
    """(len(pairs),) the trajectory's baseline between each pair's frames over the pair's own
    |t| (-); NaN for pairs that are not ok, not posed or have no translation."""
    pose_of = {fn: i for i, fn in enumerate(traj.filenames)}
    C = traj.positions_enu_m
    out = np.full(len(pairs), np.nan)
    for k, p in enumerate(pairs):
        ia, ib = pose_of.get(p.frame_a), pose_of.get(p.frame_b)
        if not p.ok or ia is None or ib is None:
            continue
        tn = float(np.linalg.norm(p.t_b_from_a_m))
        if tn > 1e-9 and np.isfinite(tn):
            out[k] = float(np.linalg.norm(C[ib] - C[ia])) / tn
    return out


def rescaled(p: PairResult, s: float) -> PairResult:
    """``p`` with its metric scale multiplied by ``s`` (a copy; a StoredPairResult keeps its
    other on-disk fields on disk)."""
    q = copy.copy(p)
    q.t_b_from_a_m = np.asarray(p.t_b_from_a_m, float) * s
    q.points_cam_a_m = np.asarray(p.points_cam_a_m, float) * s
    q.plane = np.asarray(p.plane, float) * np.array([1.0, 1.0, s])
    q.plane_dist_m = np.asarray(p.plane_dist_m, float) * s
    q.cov_m2 = np.asarray(p.cov_m2, float) * (s * s)
    q.scale_alpha = float(p.scale_alpha) * s
    return q


def rescaled_pairs(
    pairs: list[PairResult], traj: Trajectory, warnings: list[str] | None = None
) -> list[PairResult]:
    """The pairs, those whose scale departs from the trajectory's (module docstring) rescaled
    to it; the others the same objects. Unchanged without GPS (``traj.reference`` None). The
    warning naming them is logged and appended to ``warnings`` (the run report's) if given."""
    if traj.reference is None or len(pairs) < MIN_PAIRS:
        return pairs
    ratio = scale_ratios(pairs, traj)
    fin = np.isfinite(ratio)
    if fin.sum() < MIN_PAIRS:
        return pairs
    med = float(np.median(ratio[fin]))
    rel = ratio / med - 1.0
    sigma = robust_sigma(rel)  # (rel is about its median, 0; NaN entries ignored)
    limit = max(MIN_DEPARTURE, K_SIGMA * sigma)
    out = list(pairs)
    fixed = []
    for k in np.flatnonzero(fin & (np.abs(rel) > limit) & (np.abs(rel) <= MAX_DEPARTURE)):
        out[k] = rescaled(pairs[k], float(ratio[k] / med))
        how = "short" if rel[k] > 0 else "long"
        fixed.append(f"{pairs[k].frame_a} -> {pairs[k].frame_b} ({100 * abs(rel[k]):.1f} % {how})")
    if fixed:
        msg = (
            f"{len(fixed)} pair(s) disagree in scale with the trajectory by more than "
            f"{100 * limit:.1f} % and are rescaled to it (a pair's scale comes from its road "
            "plane, which a defect filling its view tilts): "
            + "; ".join(fixed[:10]) + (" ..." if len(fixed) > 10 else "")
        )  # fmt: skip
        log.warning("%s", msg)
        if warnings is not None:
            warnings.append(msg)
    return out
