"""Loop closure for revisits (issue 30): a drive that passes the same place twice.

Candidates are frame pairs (i, j) far apart in time (``min_gap_s``) whose camera centres, as the
pose graph placed them, are within ``gate_m`` of each other horizontally: the GPS gate (the
placement of two passes differs by about the GPS error, so the gate is a few GPS σ plus the
footprint's reach). For each stretch of the later pass near the earlier one, only the closest
pair (and every ``stride``-th after it) is tried; with ``FrameMatcher`` each later frame's
candidates are tried best first by image retrieval (``mapping.retrieval``), so the frame that
really saw the same ground is matched first, not the one the GPS put nearest. A candidate is
confirmed by image matching:
``match(i, j)`` returns the two frames' PairResult (the reconstruction's pair API, e.g.
``reconstruction.api.reconstruct_pair`` on the two Frames), and an ok pair becomes one more
relative constraint in the pose graph (``mapping.pose_graph.PoseGraph`` takes any frame pair),
which the bundle's windows then start from.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from roadsurf.io.drive import Drive
    from roadsurf.reconstruction.config import ReconstructionConfig
    from roadsurf.reconstruction.types import Features, PairResult

log = logging.getLogger(__name__)


def loop_candidates(
    t: np.ndarray,
    centres_m: np.ndarray,
    *,
    gate_m: float,
    min_gap_s: float,
    stride: int = 5,
    tries: int = 12,
) -> list[tuple[int, int]]:
    """Frame pairs (i, j), i < j, t_j - t_i >= min_gap_s and horizontal distance <= gate_m.

    t: (N,) frame times (s); centres_m: (N, 3) camera centres (m). Later frames j with an
    earlier frame within the gate form runs; per run the closest j and every ``stride``-th
    frame of the run (a few constraints per revisit, not one per frame). For each such j, up to
    ``tries`` earlier frames within the gate, closest first: the passes' placement differs by
    the GPS error, so the frame that really saw the same ground is often not the closest."""
    n = len(t)
    if n < 2 or gate_m <= 0:
        return []
    xy = np.asarray(centres_m, float)[:, :2]
    best = np.full(n, -1)
    dist = np.full(n, np.inf)
    for j in range(n):
        early = np.flatnonzero(t <= t[j] - min_gap_s)
        if not len(early):
            continue
        d = np.linalg.norm(xy[early] - xy[j], axis=1)
        k = int(np.argmin(d))
        if d[k] <= gate_m:
            best[j], dist[j] = early[k], d[k]
    out: list[tuple[int, int]] = []
    j = 0
    while j < n:
        if best[j] < 0:
            j += 1
            continue
        run_end = j
        while run_end + 1 < n and best[run_end + 1] >= 0:
            run_end += 1
        run = np.arange(j, run_end + 1)
        c = int(run[np.argmin(dist[run])])
        for k in sorted(set(run[(run - c) % stride == 0].tolist())):
            early = np.flatnonzero(t <= t[k] - min_gap_s)
            d = np.linalg.norm(xy[early] - xy[k], axis=1)
            near = early[np.argsort(d, kind="stable")][: int(np.sum(d <= gate_m))][:tries]
            out += [(int(i), int(k)) for i in near]
        j = run_end + 1
    return out


def confirm_loops(
    candidates: list[tuple[int, int]],
    match: Callable[[int, int], PairResult | None],
    *,
    min_inliers: int = 30,
) -> list[PairResult]:
    """The candidates whose frames match (an ok PairResult with at least ``min_inliers`` points):
    the loop constraints, at most one per later frame j (the first that matches, in the
    candidates' order). ``match`` gets frame positions (i, j) and returns the pair i -> j
    (index_a / index_b: the frames' Frame.index) or None."""
    found = []
    done: set[int] = set()
    for i, j in candidates:
        if j in done:
            continue
        p = match(i, j)
        if p is not None and p.ok and p.n_points >= min_inliers:
            found.append(p)
            done.add(j)
    log.info("loops: %d of %d candidate pair(s) confirmed", len(found), len(candidates))
    return found


class FrameMatcher:
    """``match(i, j)`` for ``confirm_loops``: the reconstruction's pair API on the drive's frames
    at positions i and j, with the features the reconstruction stage cached in RUN/features
    (the same frame is tried against several others: a few are kept in memory); and
    ``score(i, j)``, the image retrieval that orders the candidates before they are matched
    (``mapping.retrieval``). The rolling-shutter model is off for these pairs: it assumes the
    constant velocity of consecutive frames, which two passes minutes apart do not share."""

    def __init__(self, drive: Drive, rec_cfg: ReconstructionConfig, run_dir: Path) -> None:
        self.drive = drive
        self.cfg = dataclasses.replace(rec_cfg, rolling_shutter=False)
        self.run_dir = Path(run_dir)
        self.features = functools.lru_cache(maxsize=32)(self._features)

    def _features(self, i: int) -> Features:
        from roadsurf.reconstruction.stage import frame_features

        return frame_features(self.cfg, self.run_dir, self.drive.frames[i], self.drive.camera.mask)[
            0
        ]

    def score(self, i: int, j: int) -> int:
        """Retrieval score of frames i and j (``retrieval.retrieval_score``); 0 when unreadable."""
        from roadsurf.core.errors import FrameReadError
        from roadsurf.mapping.retrieval import retrieval_score

        try:
            return retrieval_score(self.features(i), self.features(j), self.cfg.features)
        except FrameReadError:
            return 0

    def __call__(self, i: int, j: int) -> PairResult | None:
        from roadsurf.core.errors import FrameReadError
        from roadsurf.reconstruction.api import reconstruct_features

        fa, fb = self.drive.frames[i], self.drive.frames[j]
        try:
            res = reconstruct_features(
                self.features(i), self.features(j), self.drive.camera, self.cfg
            )
        except FrameReadError as e:
            log.info("loops: %s-%s not matched (%s)", fa.filename, fb.filename, e)
            return None
        res.frame_a, res.frame_b, res.index_a, res.index_b = (
            fa.filename, fb.filename, fa.index, fb.index,
        )  # fmt: skip
        return res if res.ok else None


def frame_matcher(drive: Drive, rec_cfg: ReconstructionConfig, run_dir: Path) -> FrameMatcher:
    """The ``FrameMatcher`` of a drive's run folder (``match(i, j)`` and ``score(i, j)``)."""
    return FrameMatcher(drive, rec_cfg, run_dir)
