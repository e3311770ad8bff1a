"""Reconstruction stage: every consecutive valid-frame pair (i, i+1) of a drive -> PairResult.

Artifacts (atomic writes, resumable):
- ``RUN/features/<index>_<kind><max>_<digest>.npz``: keypoints + descriptors of one frame,
  computed once and reused by both pairs the frame belongs to; the digest covers the detection
  settings and the image file's identity (size, mtime);
- ``RUN/pairs/<index_a>_<index_b>.npz``: one PairResult (``reconstruction.types.save_pair``),
  written for failed pairs too (status + reason), so a resumed run skips them; beside it
  ``<index_a>_<index_b>.fingerprint`` (``pair_fingerprint``: the settings that shape a pair, the
  camera and both image files). A pair is reused only when that fingerprint still matches.
A failed pair is a PairResult with status != "ok"; nothing here raises for bad frames.

After all pairs (``cfg.normal_consensus``, proposed/rotation_aware): the road normal consensus
(``reconstruction.consensus``) re-solves the pairs whose homography decomposition took the
mirror solution, with the drive's normal (camera.yaml's mount, else the pairs' majority) as the
prior, and fails those it cannot make consistent. With ``only_pairs`` the consensus is over the
pairs of that call.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from roadsurf.core.atomic import UNREADABLE, write_text_atomic
from roadsurf.core.camera import Camera
from roadsurf.core.errors import FrameReadError, OutputError
from roadsurf.core.fingerprint import Fingerprint
from roadsurf.core.imagemask import ImageMask
from roadsurf.io.drive import Drive, Frame, read_gray
from roadsurf.io.runfolder import RunFolder, feature_filename, fingerprint_path, read_fingerprint
from roadsurf.reconstruction import consensus
from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.api import (
    reconstruct_features,
    retry_stretched,
    road_normal_in_cam,
    wants_stretch_retry,
)
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.types import Features, PairResult, load_pair, save_pair, stored

log = logging.getLogger(__name__)

# ReconstructionConfig fields that never change a pair's result
NOT_IN_PAIR_FINGERPRINT = ("probe", "workers", "overwrite", "save_features")
# in every pair's fingerprint: bump when the code changes what a pair's result is, so a run
# resumed by a newer roadsurf re-solves its pairs instead of reusing the old code's results
PAIR_VERSION = 1


def _feature_path(
    run_dir: Path, frame: Frame, cfg: ReconstructionConfig, mask: ImageMask | None = None
) -> Path:
    f = cfg.features
    # every detection setting is in the name, so a changed config never reuses stale features
    det = (f.grid_cells, f.downscale, f.max_detect_megapixels, f.contrast_threshold)
    det += (
        f.n_octave_layers,
        f.candidates_per_feature,
        f.clahe_clip,
        f.clahe_tiles,
        f.border_pad_px,
    )
    # ... and so is the image file's identity: a re-rendered frame is detected again
    fp = Fingerprint().add_repr(det).add_file_stat(frame.path, frame.filename)
    if mask is not None:  # the camera's mask drops keypoints: a new mask, new features
        fp.add_text(f"|mask {mask.digest}")
    digest = fp.hexdigest(8)
    tag = f"{f.kind}{f.max_features}_{digest}"
    return RunFolder(run_dir).features_dir / feature_filename(frame.index, tag)


def pair_fingerprint(cfg: ReconstructionConfig, camera: Camera, a: Frame, b: Frame) -> str:
    """16 hex digits (sha256) over what decides the pair (a, b): ``PAIR_VERSION``, the
    reconstruction settings (all but ``NOT_IN_PAIR_FINGERPRINT``), the camera (intrinsics, distortion, height, mount,
    readout) and both frames' index, name, file size and mtime; with a rolling shutter also
    their timestamps (the frame interval enters the geometry)."""
    settings = {k: v for k, v in asdict(cfg).items() if k not in NOT_IN_PAIR_FINGERPRINT}
    fp = Fingerprint().add_text(f"pair v{PAIR_VERSION}|").add_json(settings)
    fp.add_json(camera.fingerprint_fields())
    for f in (a, b):
        fp.add_text(f"|{f.index}|{f.filename}|").add_file_stat(f.path, "file")
        if camera.readout_s > 0:
            fp.add_text(f"{f.timestamp_s!r}|")
    return fp.hexdigest(16)


def frame_features(
    cfg: ReconstructionConfig, run_dir: Path, frame: Frame, mask: ImageMask | None = None
) -> tuple[Features, float]:
    """A frame's features from RUN/features when cached there (with these detection settings
    and this image file), else detected (and saved with ``cfg.save_features``); with the
    detection time (s, 0 when read). FrameReadError propagates."""
    path = _feature_path(run_dir, frame, cfg, mask)
    if path.is_file() and not cfg.overwrite:
        try:
            return feat.load_features(path), 0.0
        except UNREADABLE as e:
            log.warning("%s: unreadable feature cache (%s); recomputing", path, e)
    t0 = time.perf_counter()
    f = feat.detect(read_gray(frame), cfg.features, mask)
    seconds = time.perf_counter() - t0
    if cfg.save_features:
        feat.save_features(path, f)
    return f, seconds


class _FeatureCache:
    """Per-frame features: memory -> RUN/features -> detect, computed ahead in worker threads.

    OpenCV releases the GIL, so while the main thread matches and solves pair (i, i+1) the
    workers already extract the features of the next frames (2 cores used).
    """

    def __init__(
        self,
        cfg: ReconstructionConfig,
        run_dir: Path,
        frames: list[Frame],
        mask: ImageMask | None = None,
    ) -> None:
        self.cfg = cfg
        self.mask = mask
        self.run_dir = run_dir
        self.order = frames  # frames in the order they will be asked for
        self.pos = 0
        self.pos_of = {f.index: i for i, f in enumerate(frames)}
        self.charged: set[int] = set()
        self.futures: dict[int, Future[tuple[Features, float]]] = {}
        self.pool = ThreadPoolExecutor(max_workers=cfg.workers) if cfg.workers > 1 else None
        self.ahead = 2 * max(1, cfg.workers)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)

    def _compute(self, frame: Frame) -> tuple[Features, float]:
        return frame_features(self.cfg, self.run_dir, frame, self.mask)

    def _submit(self, frame: Frame) -> None:
        if frame.index in self.futures:
            return
        fut: Future[tuple[Features, float]] = Future()
        if self.pool is None:
            try:
                fut.set_result(self._compute(frame))
            except Exception as e:  # noqa: BLE001 - re-raised by get()
                fut.set_exception(e)
        else:
            fut = self.pool.submit(self._compute, frame)
        self.futures[frame.index] = fut

    def get(self, frame: Frame) -> tuple[Features, float]:
        """(features, extraction seconds, charged to the first pair only). Raises
        FrameReadError."""
        self._submit(frame)
        p = self.pos_of.get(frame.index, self.pos)
        while self.pos < len(self.order) and self.pos <= p + self.ahead:
            self._submit(self.order[self.pos])
            self.pos += 1
        for k in [k for k in self.futures if k < frame.index - 1]:  # consecutive pairs only
            self.futures.pop(k)
        f, seconds = self.futures[frame.index].result()
        if frame.index in self.charged:
            seconds = 0.0
        self.charged.add(frame.index)
        return f, seconds


def run(
    cfg: ReconstructionConfig,
    drive: Drive,
    run_dir: Path,
    *,
    only_pairs: set[tuple[int, int]] | None = None,
) -> list[PairResult]:
    """Reconstruct the consecutive valid-frame pairs of ``drive`` into ``run_dir/pairs``.

    only_pairs restricts the work to those (index_a, index_b) pairs. A cached pair file is
    reused, unless cfg.overwrite, when its stored ``pair_fingerprint`` matches the current
    settings, camera and image files. Returns the PairResults in frame order (failed ones
    included).
    """
    feat.check_available(cfg.features)  # a config problem stops the run before any work
    run_dir = Path(run_dir)
    rf = RunFolder(run_dir)
    rf.pairs_dir.mkdir(parents=True, exist_ok=True)
    frames = drive.frames
    todo = [(frames[i], frames[i + 1]) for i in range(len(frames) - 1)]
    if only_pairs is not None:
        todo = [(a, b) for a, b in todo if (a.index, b.index) in only_pairs]
    fingerprints = {(a.index, b.index): pair_fingerprint(cfg, drive.camera, a, b) for a, b in todo}
    cached: dict[tuple[int, int], PairResult] = {}
    stale = 0
    if not cfg.overwrite:
        for a, b in todo:
            key = (a.index, b.index)
            path = rf.pair(*key)
            if not path.is_file():
                continue
            if read_fingerprint(path) != fingerprints[key]:
                stale += 1  # other settings, camera or image files: recompute
                continue
            try:
                cached[key] = stored(load_pair(path), path)
            except UNREADABLE as e:
                log.warning("%s: unreadable cached pair (%s); recomputing", path, e)
    if stale:
        log.info("reconstruction: %d cached pair(s) made from other inputs; recomputing", stale)
    need: list[Frame] = []
    for a, b in todo:
        if (a.index, b.index) not in cached:
            for f in (a, b):
                if not need or need[-1].index != f.index:
                    need.append(f)
    cache = _FeatureCache(cfg, run_dir, need, drive.camera.mask)
    results: list[PairResult] = []
    try:
        for fa_frame, fb_frame in tqdm(todo, desc="reconstruction", unit="pair", leave=False):
            key = (fa_frame.index, fb_frame.index)
            if key in cached:
                results.append(cached[key])
                continue
            res = _one_pair(cfg, drive, cache, fa_frame, fb_frame)
            path = rf.pair(*key)
            # the old fingerprint goes first: a pair file never sits beside another's fingerprint
            fingerprint_path(path).unlink(missing_ok=True)
            save_pair(path, res)
            write_text_atomic(fingerprint_path(path), fingerprints[key] + "\n")
            results.append(stored(res, path))  # the arrays no later stage reads stay on disk
        if cfg.normal_consensus and cfg.method in ("proposed", "rotation_aware"):
            _normal_consensus(cfg, drive, cache, results, rf, fingerprints)
    finally:
        cache.close()
    counts = Counter(r.status for r in results)
    log.info(
        "reconstruction: %d pairs (%d cached), status %s", len(results), len(cached), dict(counts)
    )
    return results


def _normal_consensus(
    cfg: ReconstructionConfig,
    drive: Drive,
    cache: _FeatureCache,
    results: list[PairResult],
    rf: RunFolder,
    fingerprints: dict[tuple[int, int], str],
) -> None:
    """Re-decide, in place, the pairs whose road normal is far from the drive's consensus
    (``reconstruction.consensus``): re-solved with the consensus normal as the prior, or failed
    with the reason. Changed pairs are saved again under the same fingerprint: a resumed run
    loads the re-decided pair, and the consensus, recomputed, keeps it."""
    by_index = {f.index: f for f in drive.frames}

    def resolve(i: int, normal: np.ndarray) -> PairResult:
        r = results[i]
        return _one_pair(
            cfg, drive, cache, by_index[r.index_a], by_index[r.index_b], road_normal_cam=normal
        )

    _, changed = consensus.apply(results, drive.camera.K, road_normal_in_cam(drive.camera), resolve)
    for i in changed:
        key = (results[i].index_a, results[i].index_b)
        path = rf.pair(*key)
        fingerprint_path(path).unlink(missing_ok=True)
        save_pair(path, results[i])
        write_text_atomic(fingerprint_path(path), fingerprints[key] + "\n")


def _one_pair(
    cfg: ReconstructionConfig,
    drive: Drive,
    cache: _FeatureCache,
    a: Frame,
    b: Frame,
    *,
    road_normal_cam: np.ndarray | None = None,
) -> PairResult:
    try:
        fa, sa = cache.get(a)
        fb, sb = cache.get(b)
        t_feat = sa + sb
        dt = b.timestamp_s - a.timestamp_s  # the rolling shutter's frame interval
        res = reconstruct_features(
            fa, fb, drive.camera, cfg, frame_dt_s=dt, road_normal_cam=road_normal_cam
        )
        if wants_stretch_retry(res, cfg):
            res = _stretch_retry(cfg, drive, res, fa, b, dt, road_normal_cam)
        res.timings_s["features"] = t_feat
    except FrameReadError as e:
        res = PairResult(a.filename, b.filename, a.index, b.index, cfg.method, "unreadable_frame")
        res.reason = str(e)
    except OutputError:
        raise  # disk full / unwritable output: the run stops with its one-line error
    except Exception as e:  # noqa: BLE001 - a pair must never stop the drive run
        log.exception("pair %s -> %s failed unexpectedly", a.filename, b.filename)
        res = PairResult(a.filename, b.filename, a.index, b.index, cfg.method, "geometry_failed")
        res.reason = f"unexpected {type(e).__name__}: {e}"
    res.frame_a, res.frame_b, res.index_a, res.index_b = a.filename, b.filename, a.index, b.index
    if not res.ok:
        log.debug("pair %s -> %s: %s (%s)", a.filename, b.filename, res.status, res.reason)
    return res


def _stretch_retry(
    cfg: ReconstructionConfig,
    drive: Drive,
    res: PairResult,
    fa: Features,
    b: Frame,
    dt: float,
    road_normal_cam: np.ndarray | None,
) -> PairResult:
    """``api.retry_stretched`` on a pair short of matches; an image b that cannot be read now
    (its features came from the cache) keeps the pair's own failure."""
    try:
        gb = read_gray(b)
    except FrameReadError as e:
        log.debug("stretch retry of %s skipped: %s", b.filename, e)
        return res
    out = retry_stretched(
        res, fa, gb, drive.camera, cfg, frame_dt_s=dt, road_normal_cam=road_normal_cam
    )
    if out.ok:
        log.info(
            "pair -> %s matched with image b compressed vertically to %.2f "
            "(perspective / rolling-shutter stretch)",
            b.filename,
            out.stretch_b,
        )
    return out
