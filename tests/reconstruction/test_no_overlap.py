"""Two textured frames of different ground (spd2 33-34, a change of pothole): enough ratio-test
matches by chance, but fewer than min_matches move like one road. That is no overlap (the
segment after it is kept apart from mapped ground), not a lack of matches."""

from __future__ import annotations

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.reconstruction.api import reconstruct_features
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.types import Features


def _features(n_true: int, n_chance: int, seed: int = 0) -> tuple[Features, Features]:
    """n_true matches that move 40 px right, n_chance matched at random places, 30 unmatched
    keypoints per frame."""
    rng = np.random.default_rng(seed)
    n = n_true + n_chance
    desc = rng.normal(size=(n, 128)).astype(np.float32)
    pa = rng.uniform([50, 50], [900, 700], (n, 2))
    pb = pa + [40.0, 0.0] + rng.normal(0, 0.3, (n, 2))
    pb[n_true:] = rng.uniform([0, 0], [1000, 760], (n_chance, 2))
    extra = [rng.normal(size=(30, 128)).astype(np.float32) for _ in range(2)]
    ka = np.vstack([pa, rng.uniform(0, 700, (30, 2))]).astype(np.float32)
    kb = np.vstack([pb, rng.uniform(0, 700, (30, 2))]).astype(np.float32)
    fa = Features(ka, np.vstack([desc, extra[0]]), "sift")
    fb = Features(kb, np.vstack([desc + 0.01, extra[1]]), "sift")
    return fa, fb


def test_chance_matches_that_no_road_motion_explains_are_no_overlap() -> None:
    cam = Camera(1024, 768, 1000.0, 1000.0, 511.5, 383.5, 1.1, 10.0)
    cfg = ReconstructionConfig()
    res = reconstruct_features(*_features(20, 20), cam, cfg)
    assert res.n_matches >= cfg.min_matches
    assert res.status == "no_overlap", (res.status, res.reason)
    assert "agree with one motion" in res.reason
    # the same frames without the prior say too few matches (the prior is the evidence)
    res = reconstruct_features(*_features(20, 20), cam, ReconstructionConfig(motion_prior=False))
    assert res.status != "no_overlap"
