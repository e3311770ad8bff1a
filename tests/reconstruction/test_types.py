from __future__ import annotations

import numpy as np

from roadsurf.reconstruction.api import reconstruct_pair
from roadsurf.reconstruction.config import FeatureConfig, ReconstructionConfig
from roadsurf.reconstruction.types import PairResult, load_pair, save_pair
from tests.reconstruction.conftest import render_pair


def test_pair_result_round_trip(tmp_path, cam) -> None:
    a, b = render_pair(cam, seed=2)
    res = reconstruct_pair(
        a, b, cam, ReconstructionConfig(features=FeatureConfig(max_features=500))
    )
    assert res.ok
    res.frame_a, res.frame_b, res.index_a, res.index_b = "a.jpg", "b.jpg", 3, 4
    back = load_pair(save_pair(tmp_path / "p.npz", res))
    assert isinstance(back, PairResult)
    for name in (
        "points_cam_a_m",
        "px_a",
        "px_b",
        "cov_m2",
        "plane_dist_m",
        "R_b_from_a",
        "H",
        "F",
        "match_idx",
    ):
        np.testing.assert_array_equal(getattr(back, name), getattr(res, name))
    assert (back.frame_a, back.index_b, back.status, back.method) == ("a.jpg", 4, "ok", res.method)
    assert back.timings_s == res.timings_s
    assert back.scale_alpha == res.scale_alpha


def test_failed_pair_round_trip(tmp_path) -> None:
    res = PairResult("a", "b", 0, 1, "proposed", "no_overlap", "nothing matched")
    back = load_pair(save_pair(tmp_path / "f.npz", res))
    assert back.status == "no_overlap" and back.reason == "nothing matched" and back.n_points == 0
