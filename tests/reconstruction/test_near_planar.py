"""A pair whose homography leaves most matches out is near-planar when those outliers are
mismatches, and not when they are 3D structure off the road (``estimators``, OFF_PLANE_SHARE)."""

from __future__ import annotations

import numpy as np

from roadsurf.core.camera import px_from_cam
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.estimators import estimate_matches
from roadsurf.simulation.points import PointScene, simulate_points

# the motion prior off: the homography's near-planarity test is what is checked here
CFG = ReconstructionConfig(method="rotation_aware", motion_prior=False)
SCENE = PointScene(sigma_px=0.2, n_points=300)


def _with_outliers(kind: str, share: float, seed: int) -> tuple[np.ndarray, ...]:
    pp = simulate_points(SCENE, seed)
    rng = np.random.default_rng(seed)
    n_out = int(share * len(pp.px_a))
    px_a, px_b = pp.px_a.copy(), pp.px_b.copy()
    if kind == "mismatch":  # b's match 5-25 px off, in any direction
        ang = rng.uniform(0, 2 * np.pi, n_out)
        rad = rng.uniform(5, 25, n_out)
        px_b[:n_out] += np.c_[np.cos(ang), np.sin(ang)] * rad[:, None]
    else:  # points 10-40 cm above the road (a kerb, a car's bumper), seen by both cameras
        X = pp.X_a_m[:n_out].copy()
        X *= (1 - rng.uniform(0.1, 0.4, n_out) / X[:, 2])[:, None]
        Xb = X @ pp.R_b_from_a.T + pp.t_b_from_a_m
        px_a[:n_out] = px_from_cam(X, pp.K) + rng.normal(0, SCENE.sigma_px, (n_out, 2))
        px_b[:n_out] = px_from_cam(Xb, pp.K) + rng.normal(0, SCENE.sigma_px, (n_out, 2))
    return px_a, px_b, pp.K, pp.h_measured_m


def test_mismatches_beyond_half_do_not_make_a_plane_non_planar() -> None:
    for seed in range(3):
        px_a, px_b, K, h = _with_outliers("mismatch", 0.6, seed)
        res = estimate_matches(px_a, px_b, K, h, CFG)
        assert res.status == "ok", res.reason
        assert res.outlier_ratio_h >= CFG.near_planar_max_outlier


def test_structure_off_the_plane_is_not_near_planar() -> None:
    for seed in range(3):
        px_a, px_b, K, h = _with_outliers("structure", 0.6, seed)
        res = estimate_matches(px_a, px_b, K, h, CFG)
        assert res.status == "not_near_planar", res.reason
        assert "lie off the plane" in res.reason


def test_the_epipolar_share_tells_mismatches_from_structure() -> None:
    """The share of the homography's outliers on their epipolar lines: mismatches well below
    OFF_PLANE_SHARE, points off the plane well above it (docs/reconstruction.md quotes it)."""
    from roadsurf.reconstruction.estimators import OFF_PLANE_SHARE, _outliers_on_epipolar_lines
    from roadsurf.reconstruction.pose_planar import estimate_homography

    for kind, lo, hi in (("mismatch", 0.0, 0.3), ("structure", 0.9, 1.0)):
        for seed in range(3):
            px_a, px_b, K, _ = _with_outliers(kind, 0.6, seed)
            H, inl, _ = estimate_homography(px_a, px_b, CFG)
            share = _outliers_on_epipolar_lines(px_a, px_b, H, inl, K, CFG, None)
            assert share is not None and lo <= share <= hi, (kind, seed, share)
    assert 0.3 < OFF_PLANE_SHARE < 0.9
