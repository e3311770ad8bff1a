"""Road-normal consensus (issue 28, spd2): a pair whose homography decomposition took the mirror
solution is re-solved with the drive's normal; a pair that cannot be made consistent fails with
a reason. Seeded synthetic normals and matches (``tests.reconstruction.test_tilted.make_pair``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from roadsurf.reconstruction import consensus
from roadsurf.reconstruction.api import reconstruct_matches, road_normal_in_cam
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.pose_planar import plane_solutions
from roadsurf.reconstruction.types import PairResult
from tests.reconstruction.test_tilted import angle_deg, make_pair


def _tilt(n: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    """n turned by deg about a random axis perpendicular to it."""
    a = np.cross(n, rng.normal(size=3))
    a /= np.linalg.norm(a)
    r = np.radians(deg)
    return np.cos(r) * n + np.sin(r) * a


def test_decide_resolves_a_mirror_and_fails_an_inconsistent_pair() -> None:
    rng = np.random.default_rng(0)
    n0 = np.array([0.0, 0.6, 0.8])
    chosen = [_tilt(n0, abs(rng.normal(0, 2.0)), rng) for _ in range(10)]
    alts = [_tilt(n0, 80.0 + rng.uniform(-10, 10), rng)[None, :] for _ in range(10)]
    chosen[3], alts[3] = alts[3][0], chosen[3][None, :]  # pair 3 took the mirror
    chosen[7], alts[7] = _tilt(n0, 70.0, rng), _tilt(n0, 85.0, rng)[None, :]  # neither fits
    alts[5] = np.zeros((0, 3))  # a pair with one decomposition only
    out = consensus.decide(np.array(chosen), alts)
    assert out is not None and out.source == "pairs"
    assert angle_deg(out.normal_cam, n0) < 2.0
    assert consensus.TOL_MIN_DEG <= out.tol_deg <= consensus.TOL_MAX_DEG
    actions = [d.action for d in out.decisions]
    assert actions[3] == "resolve" and actions[7] == "fail"
    assert actions.count("keep") == 8
    d7 = out.decisions[7]
    assert d7.chosen_deg > 60 and d7.best_alt_deg > 75
    assert f"{d7.chosen_deg:.1f}°" in d7.reason and f"{d7.best_alt_deg:.1f}°" in d7.reason


def test_decide_uses_the_mount_when_given_and_needs_three_pairs_without() -> None:
    n0 = np.array([0.0, 0.0, 1.0])
    mount = np.array([0.0, np.sin(np.radians(40)), np.cos(np.radians(40))])
    out = consensus.decide(np.array([n0, n0]), [np.zeros((0, 3))] * 2, mount)
    assert out is not None and out.source == "camera.yaml"
    np.testing.assert_allclose(out.normal_cam, mount)
    assert [d.action for d in out.decisions] == ["fail", "fail"]  # 40° off a given mount
    assert consensus.decide(np.array([n0, n0]), [np.zeros((0, 3))] * 2) is None
    with pytest.raises(ValueError, match="one per pair"):
        consensus.decide(np.array([n0, n0, n0]), [np.zeros((0, 3))])


def test_a_pair_on_the_mirror_decomposition_is_re_solved_with_the_consensus() -> None:
    """Five pairs of a 45° camera with an unknown mount; one is forced onto the mirror
    decomposition (a wrong road-normal prior, as spd2's steep hand-held shots got by
    themselves). The consensus re-solves it: normal, rotation and translation back on the
    truth."""
    cfg = ReconstructionConfig()
    pairs, truth, results = [], [], []
    for k in range(5):
        tp = make_pair(45.0, 2.0, -3.0 + 2 * k, seed=10 + k)
        cam = replace(tp.camera, mount_deg=None)
        pairs.append((tp, cam))
        truth.append(-tp.up_cam_a)
        results.append(reconstruct_matches(tp.px_a, tp.px_b, cam, cfg))
    assert all(r.ok for r in results)
    # pair 2 on the mirror: its road homography's other decomposition as the prior
    tp, cam = pairs[2]
    sols = plane_solutions(results[2].px_a, results[2].H, cam.K)
    mirror = next(m for _, _, m, _ in sols if angle_deg(m, truth[2]) > 45)
    results[2] = reconstruct_matches(tp.px_a, tp.px_b, cam, cfg, road_normal_cam=mirror)
    bad_normal = consensus.plane_normal_cam(results[2].plane)
    assert results[2].ok and angle_deg(bad_normal, truth[2]) > 45

    def resolve(i: int, normal: np.ndarray) -> PairResult:
        tp_i, cam_i = pairs[i]
        return reconstruct_matches(tp_i.px_a, tp_i.px_b, cam_i, cfg, road_normal_cam=normal)

    cons, changed = consensus.apply(results, cam.K, None, resolve)
    assert cons is not None and changed == [2]
    assert angle_deg(cons.normal_cam, truth[0]) < 2.0
    r = results[2]
    assert r.ok
    assert angle_deg(consensus.plane_normal_cam(r.plane), truth[2]) < 1.0
    R_err = r.R_b_from_a.T @ tp.R_b_from_a
    assert np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 0.5
    assert angle_deg(r.t_b_from_a_m, tp.t_b_from_a_m) < 2.0


def test_a_pair_that_stays_inconsistent_fails_with_a_reason() -> None:
    """With the mount in camera.yaml the consensus is the mount's normal; a pair whose road is
    40° off it (a wrong mount for that pair, or a non-road plane) has no decomposition near it:
    it fails (geometry_failed) and the reason gives the angles."""
    cfg = ReconstructionConfig()
    tp = make_pair(45.0, 2.0, -3.0, seed=3)
    other = make_pair(5.0, 0.0, 0.0, seed=4)  # a camera looking nearly straight down
    results = [reconstruct_matches(tp.px_a, tp.px_b, tp.camera, cfg) for _ in range(3)]
    results.append(reconstruct_matches(other.px_a, other.px_b, other.camera, cfg))
    assert all(r.ok for r in results)
    calls: list[int] = []

    def resolve(i: int, normal: np.ndarray) -> PairResult:
        calls.append(i)
        return reconstruct_matches(
            other.px_a, other.px_b, other.camera, cfg, road_normal_cam=normal
        )

    cons, changed = consensus.apply(results, tp.camera.K, road_normal_in_cam(tp.camera), resolve)
    assert cons is not None and cons.source == "camera.yaml" and changed == [3]
    assert results[3].status == "geometry_failed"
    assert "from the drive's" in results[3].reason and "tolerance" in results[3].reason
    assert all(r.ok for r in results[:3])
