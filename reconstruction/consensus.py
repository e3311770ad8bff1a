"""Road-normal consensus over a drive's pairs: re-decide homography decompositions that took the
mirror solution.

A road-plane homography has two physically distinct decompositions (``pose_planar.
plane_solutions``): the road (normal n, motion t) and a mirror whose plane normal lies near the
direction of travel. Each pair picks one by priors on its own; with a steep camera and no mount
in camera.yaml those priors can pick the mirror (spd2: 3 of 26 pairs, their normals 77-83° off
the others'). The camera is rigid on the vehicle, so the road's normal in camera coordinates is
nearly the same for every pair: once all pairs are solved, a consensus normal decides.

- The consensus normal n̄ is the mount's road normal when camera.yaml gives the mount (used as
  given), else a majority vote: every candidate normal of every pair is a hypothesis, scored by
  the number of pairs whose chosen normal lies within ``SUPPORT_DEG`` of it; the winner is
  refined to the mean of its supporters. Mirror normals follow each pair's own motion, so they
  only gather support when most pairs share one direction of travel and chose the mirror, which
  the per-pair priors make rare.
- The spread: the angles θ_i of the pairs' nearest candidates to n̄ are modelled as Rayleigh
  (a 2-D Gaussian tilt of σ per axis: vibration, grade, cross-fall, a hand-held camera's
  aim); σ̂ = median(θ) / √(2 ln 2). The tolerance τ = clip(``RAYLEIGH_Q``·σ̂, ``TOL_MIN_DEG``,
  ``TOL_MAX_DEG``) keeps a good pair with probability 1 − 10⁻³.
- Per pair: chosen normal within τ -> keep; else an alternative within τ -> re-solve the pair
  with n̄ as its road-normal prior; else fail (``geometry_failed``, the angles in the reason).

``decide`` is a pure function of arrays (callable from a worker process); ``pair_normals``
reads a PairResult; ``reconstruction.stage`` applies the decisions.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from roadsurf.core.fits import RAYLEIGH_MEDIAN
from roadsurf.reconstruction.pose_planar import plane_solutions
from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

MIN_PAIRS = 3  # fewer pairs with candidates and no mount: no consensus (a majority needs 3)
RAYLEIGH_Q = math.sqrt(-2.0 * math.log(1e-3))  # 3.72: P(θ > q σ) = 1e-3 for a Rayleigh angle
# Floor of τ (deg): on a vehicle σ̂ is 1-2° (τ would be 4-7°), but a grade change, a crown or a
# braking pitch moves the road normal a few degrees for a whole pair; 20° is a third of the
# smallest angle between a road and a mirror normal (a mirror normal lies near the direction of
# travel, 90° from the road's for travel along the road; >= 58° on spd2's hand-held shots).
TOL_MIN_DEG = 20.0
TOL_MAX_DEG = 30.0  # cap of τ (deg): half-way to the nearest mirror normal expected (60°)
SUPPORT_DEG = TOL_MIN_DEG  # a pair supports a hypothesis within this (deg), before σ̂ is known


@dataclass(frozen=True)
class Decision:
    """What to do with one pair: ``action`` keep | resolve | fail, with the angles (deg)."""

    action: str
    chosen_deg: float  # chosen normal to the consensus
    best_alt_deg: float  # nearest alternative candidate to the consensus (nan: none)
    reason: str = ""


@dataclass
class NormalConsensus:
    """The consensus road normal in camera coordinates and one Decision per input pair."""

    normal_cam: np.ndarray  # (3,) unit, downward (towards the road), camera coordinates
    source: str  # "camera.yaml" | "pairs"
    spread_deg: float  # σ̂ (deg) per axis of the pairs' normals about normal_cam
    tol_deg: float  # τ (deg)
    n_pairs: int
    decisions: list[Decision] = field(default_factory=list)


def _angles_deg(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(k,) angles (deg) between the rows of v (k, 3) and the unit 3-vector n."""
    v = np.atleast_2d(v)
    c = (v @ n) / np.maximum(np.linalg.norm(v, axis=1), 1e-300)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-300)


def decide(
    chosen: np.ndarray,
    alternatives: list[np.ndarray],
    mount_normal_cam: np.ndarray | None = None,
) -> NormalConsensus | None:
    """Consensus road normal and per-pair decisions (pure).

    chosen (N, 3): each pair's road normal (downward, camera a; need not be unit);
    alternatives: per pair a (k_i, 3) array of its other decompositions' normals (k_i may be 0);
    mount_normal_cam (3,): the mount's downward road normal when camera.yaml gives it, else
    None. Returns None without a mount and with fewer than ``MIN_PAIRS`` pairs.
    """
    chosen = np.asarray(chosen, float).reshape(-1, 3)
    if len(alternatives) != len(chosen):
        raise ValueError(
            f"normal consensus: {len(chosen)} chosen normals but {len(alternatives)} "
            "alternative lists (one per pair expected)"
        )
    alts = [np.asarray(a, float).reshape(-1, 3) for a in alternatives]
    chosen = chosen / np.maximum(np.linalg.norm(chosen, axis=1, keepdims=True), 1e-300)
    n = len(chosen)
    if mount_normal_cam is not None:
        nbar = _unit(np.asarray(mount_normal_cam, float).reshape(3))
        source = "camera.yaml"
    else:
        if n < MIN_PAIRS:
            return None
        hyps = np.vstack([chosen, *alts])
        support = np.array(
            [int(np.sum(_angles_deg(chosen, _unit(h)) <= SUPPORT_DEG)) for h in hyps]
        )
        h = _unit(hyps[int(np.argmax(support))])  # first best: a chosen normal wins a tie
        # refine on the supporters: every pair's candidate nearest the hypothesis, if close
        near = [_nearest(chosen[i], alts[i], h) for i in range(n)]
        sup = np.array([v for v, a in near if a <= SUPPORT_DEG])
        nbar = _unit(sup.mean(axis=0)) if len(sup) else h
        source = "pairs"
    theta = np.array([_nearest(chosen[i], alts[i], nbar)[1] for i in range(n)])
    sigma = float(np.median(theta)) / RAYLEIGH_MEDIAN if n else 0.0
    tol = float(np.clip(RAYLEIGH_Q * sigma, TOL_MIN_DEG, TOL_MAX_DEG))
    out = NormalConsensus(nbar, source, sigma, tol, n)
    for i in range(n):
        a_c = float(_angles_deg(chosen[i], nbar)[0])
        a_alt = _angles_deg(alts[i], nbar) if len(alts[i]) else np.array([np.nan])
        best = float(np.nanmin(a_alt)) if np.isfinite(a_alt).any() else float("nan")
        if a_c <= tol:
            out.decisions.append(Decision("keep", a_c, best))
        elif np.isfinite(best) and best <= tol:
            out.decisions.append(
                Decision(
                    "resolve",
                    a_c,
                    best,
                    f"road normal {a_c:.1f}° from the drive's ({source}, tolerance {tol:.1f}°); "
                    f"its other homography decomposition is {best:.1f}° off: re-solved with the "
                    "drive's normal as the prior",
                )
            )
        else:
            alt_txt = (
                "it has no other decomposition"
                if not np.isfinite(best)
                else (f"its other decomposition is {best:.1f}° off")
            )
            out.decisions.append(
                Decision(
                    "fail",
                    a_c,
                    best,
                    f"road normal {a_c:.1f}° from the drive's ({source}; tolerance {tol:.1f}° = "
                    f"{RAYLEIGH_Q:.2f} x the pairs' spread {sigma:.1f}°, within "
                    f"[{TOL_MIN_DEG:.0f}, {TOL_MAX_DEG:.0f}]°) and {alt_txt}: the pair does not "
                    "fit a camera rigid on the vehicle (a wrong match set, or a non-road plane)",
                )
            )
    return out


def _nearest(chosen: np.ndarray, alts: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, float]:
    """(candidate, angle deg) of the pair's candidate (chosen or alternative) nearest n."""
    cands = np.vstack([chosen[None, :], alts]) if len(alts) else chosen[None, :]
    ang = _angles_deg(cands, n)
    k = int(np.argmin(ang))
    return _unit(cands[k]), float(ang[k])


def plane_normal_cam(plane: np.ndarray) -> np.ndarray:
    """(3,) unit downward normal of the plane Z = p0 X + p1 Y + p2 (camera coordinates)."""
    p = np.asarray(plane, float)
    return _unit(np.array([-p[0], -p[1], 1.0]))


def pair_normals(res: PairResult, K: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(chosen (3,), alternatives (k, 3)) unit downward road normals of an ok pair: its fitted
    plane's, and the homography's other decompositions' (``plane_solutions`` of the stored
    road homography; the candidate nearest the fitted plane is the chosen one). None for a
    failed pair or one without a homography (classic, colmap, stereo)."""
    if not res.ok or res.n_points < 3 or not np.all(np.isfinite(res.H)):
        return None
    if not np.all(np.isfinite(res.plane)):
        return None
    chosen = plane_normal_cam(res.plane)
    sols = plane_solutions(np.asarray(res.px_a, float), np.asarray(res.H, float), K)
    if not sols:
        return chosen, np.zeros((0, 3))
    normals = np.array([_unit(m) for _, _, m, _ in sols])
    k = int(np.argmin(_angles_deg(normals, chosen)))
    return chosen, np.delete(normals, k, axis=0)


def apply(
    results: list[PairResult],
    K: np.ndarray,
    mount_normal_cam: np.ndarray | None,
    resolve: Callable[[int, np.ndarray], PairResult],
) -> tuple[NormalConsensus | None, list[int]]:
    """Re-decide ``results`` in place: ``resolve(i, normal_cam)`` re-solves pair i with the
    consensus normal as its road-normal prior; a re-solved pair that fails or is still beyond
    the tolerance, and a pair with no candidate within it, become ``geometry_failed`` with the
    reason. K (3, 3) intrinsics of the undistorted pixels. Returns (the consensus or None,
    positions of the changed pairs)."""
    idx, chosen, alts = [], [], []
    for i, r in enumerate(results):
        pn = pair_normals(r, K)
        if pn is not None:
            idx.append(i)
            chosen.append(pn[0])
            alts.append(pn[1])
    cons = decide(np.array(chosen).reshape(-1, 3), alts, mount_normal_cam) if idx else None
    if cons is None:
        return None, []
    log.info(
        "road normal consensus (%s) from %d pairs: spread %.1f deg, tolerance %.1f deg",
        cons.source,
        cons.n_pairs,
        cons.spread_deg,
        cons.tol_deg,
    )
    changed: list[int] = []
    for i, dec in zip(idx, cons.decisions, strict=True):
        if dec.action == "keep":
            continue
        old = results[i]
        name = f"pair {old.frame_a} -> {old.frame_b}"
        if dec.action == "resolve":
            res = resolve(i, cons.normal_cam)
            pn = pair_normals(res, K)
            ang = float("nan") if pn is None else float(_angles_deg(pn[0], cons.normal_cam)[0])
            if res.ok and ang <= cons.tol_deg:
                log.warning("%s: %s; now %.1f deg off", name, dec.reason, ang)
            else:
                why = res.reason if not res.ok else f"its normal is still {ang:.1f}° off"
                res = failed_like(old, f"{dec.reason}, but the re-solved pair failed ({why})")
                log.warning("%s failed: %s", name, res.reason)
        else:
            res = failed_like(old, dec.reason)
            log.warning("%s failed: %s", name, dec.reason)
        results[i] = res
        changed.append(i)
    return cons, changed


def failed_like(old: PairResult, reason: str) -> PairResult:
    """A ``geometry_failed`` PairResult for the frames of ``old`` (counts, timings kept)."""
    res = PairResult(
        old.frame_a, old.frame_b, old.index_a, old.index_b, old.method, "geometry_failed", reason
    )
    res.n_features_a, res.n_features_b = old.n_features_a, old.n_features_b
    res.n_matches = old.n_matches
    res.timings_s = dict(old.timings_s)
    return res
