"""Image retrieval for loop closure (issue 30): which earlier frame within the GPS gate most
likely shows the same ground as a later one.

Road images have no landmarks: a global descriptor (bag of words, VLAD) sees asphalt as
asphalt everywhere and ranks every frame of the road alike. What does tell two passes apart is
that the same grains of the same patch of asphalt give the same SIFT descriptors, so the
retrieval score is the number of mutual ratio-test matches between the ``k`` strongest,
grid-spread keypoints of the two frames (the frames' first ``k`` features: the detector orders
them round-robin over its grid, ``features._spread``). With k = 300 it costs ~10 ms a candidate,
against ~300 ms for the full pair it replaces as the first try, and frames that share no ground
score a handful of chance matches.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.config import FeatureConfig
from roadsurf.reconstruction.types import Features

RETRIEVAL_KEYPOINTS = 300  # strongest grid-spread keypoints compared per frame (count)


def retrieval_score(
    fa: Features, fb: Features, cfg: FeatureConfig, k: int = RETRIEVAL_KEYPOINTS
) -> int:
    """Mutual ratio-test matches (count) between the first ``k`` features of two frames
    (brute force: exact and deterministic at this size)."""
    a = Features(fa.keypoints_px[:k], fa.descriptors[:k], fa.kind)
    b = Features(fb.keypoints_px[:k], fb.descriptors[:k], fb.kind)
    ia, _ = feat.match(a, b, replace(cfg, matcher="bf", mutual=True))
    return int(len(ia))


def rank_candidates(
    candidates: list[tuple[int, int]], score: Callable[[int, int], int]
) -> list[tuple[int, int]]:
    """The loop candidates (i, j) with each later frame j's earlier frames ordered by
    ``score(i, j)``, best first (ties keep the given order, the GPS distance); the order of the
    later frames is kept. Each score is computed once."""
    groups: dict[int, list[tuple[int, int]]] = {}
    for c in candidates:
        groups.setdefault(c[1], []).append(c)
    out: list[tuple[int, int]] = []
    for j in dict.fromkeys(c[1] for c in candidates):
        group = groups[j]
        s = np.array([score(i, jj) for i, jj in group])
        out += [group[n] for n in np.argsort(-s, kind="stable")]
    return out
