"""Reconstruction stage: every consecutive valid-frame pair (i, i+1) of a drive -> PairResult.

Artifacts (atomic writes, resumable):
- ``RUN/features/<index>_<kind><max>.npz``: keypoints + descriptors of one frame, computed once
  and reused by both pairs the frame belongs to;
- ``RUN/pairs/<index_a>_<index_b>.npz``: one PairResult (``reconstruction.types.save_pair``),
  written for failed pairs too (status + reason), so a resumed run skips them.
A failed pair is a PairResult with status != "ok"; nothing here raises for bad frames.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path

from tqdm import tqdm

from reconstruction import features as feat
from reconstruction.api import reconstruct_features
from reconstruction.config import ReconstructionConfig
from reconstruction.types import Features, PairResult, load_pair, pair_filename, save_pair
from roadsurf.drive import Drive, Frame, read_gray
from roadsurf.errors import FrameReadError

log = logging.getLogger(__name__)


def _feature_path(run_dir: Path, frame: Frame, cfg: ReconstructionConfig) -> Path:
    f = cfg.features
    tag = f"{f.kind}{f.max_features}g{f.grid_cells}s{f.downscale:g}"
    return run_dir / "features" / f"{frame.index:06d}_{tag}.npz"


class _FeatureCache:
    """Per-frame features: memory (last few frames) -> RUN/features -> detect."""

    def __init__(self, cfg: ReconstructionConfig, run_dir: Path) -> None:
        self.cfg = cfg
        self.run_dir = run_dir
        self.mem: dict[int, Features] = {}
        self.seconds = 0.0

    def get(self, frame: Frame) -> Features:
        if frame.index in self.mem:
            return self.mem[frame.index]
        path = _feature_path(self.run_dir, frame, self.cfg)
        f = None
        if path.is_file() and not self.cfg.overwrite:
            try:
                f = feat.load_features(path)
            except (OSError, ValueError, KeyError) as e:
                log.warning("%s: unreadable feature cache (%s); recomputing", path, e)
        if f is None:
            t0 = time.perf_counter()
            f = feat.detect(read_gray(frame), self.cfg.features)  # FrameReadError propagates
            self.seconds = time.perf_counter() - t0
            if self.cfg.save_features:
                feat.save_features(path, f)
        else:
            self.seconds = 0.0
        if len(self.mem) >= 4:  # consecutive pairs only need the previous frame
            self.mem.pop(min(self.mem))
        self.mem[frame.index] = f
        return f


def run(
    cfg: ReconstructionConfig,
    drive: Drive,
    run_dir: Path,
    *,
    only_pairs: set[tuple[int, int]] | None = None,
) -> list[PairResult]:
    """Reconstruct the consecutive valid-frame pairs of ``drive`` into ``run_dir/pairs``.

    only_pairs restricts the work to those (index_a, index_b) pairs. Cached pair files are
    reused unless cfg.overwrite. Returns the PairResults in frame order (failed ones included).
    """
    run_dir = Path(run_dir)
    pairs_dir = run_dir / "pairs"
    pairs_dir.mkdir(parents=True, exist_ok=True)
    frames = drive.frames
    todo = [(frames[i], frames[i + 1]) for i in range(len(frames) - 1)]
    if only_pairs is not None:
        todo = [(a, b) for a, b in todo if (a.index, b.index) in only_pairs]
    cache = _FeatureCache(cfg, run_dir)
    results: list[PairResult] = []
    n_cached = 0
    for fa_frame, fb_frame in tqdm(todo, desc="reconstruction", unit="pair", leave=False):
        path = pairs_dir / pair_filename(fa_frame.index, fb_frame.index)
        if path.is_file() and not cfg.overwrite:
            try:
                res = load_pair(path)
                if res.method == cfg.method:
                    results.append(res)
                    n_cached += 1
                    continue
            except (OSError, ValueError, KeyError) as e:
                log.warning("%s: unreadable cached pair (%s); recomputing", path, e)
        res = _one_pair(cfg, drive, cache, fa_frame, fb_frame)
        save_pair(path, res)
        results.append(res)
    counts = Counter(r.status for r in results)
    log.info(
        "reconstruction: %d pairs (%d cached), status %s", len(results), n_cached, dict(counts)
    )
    return results


def _one_pair(
    cfg: ReconstructionConfig, drive: Drive, cache: _FeatureCache, a: Frame, b: Frame
) -> PairResult:
    try:
        t_feat = 0.0
        fa = cache.get(a)
        t_feat += cache.seconds
        fb = cache.get(b)
        t_feat += cache.seconds
        res = reconstruct_features(fa, fb, drive.camera, cfg)
        res.timings_s["features"] = t_feat
    except FrameReadError as e:
        res = PairResult(a.filename, b.filename, a.index, b.index, cfg.method, "unreadable_frame")
        res.reason = str(e)
    except Exception as e:  # noqa: BLE001 - a pair must never stop the drive run
        log.exception("pair %s -> %s failed unexpectedly", a.filename, b.filename)
        res = PairResult(a.filename, b.filename, a.index, b.index, cfg.method, "geometry_failed")
        res.reason = f"unexpected {type(e).__name__}: {e}"
    res.frame_a, res.frame_b, res.index_a, res.index_b = a.filename, b.filename, a.index, b.index
    if not res.ok:
        log.debug("pair %s -> %s: %s (%s)", a.filename, b.filename, res.status, res.reason)
    return res
