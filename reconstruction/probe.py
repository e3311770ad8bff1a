"""The cheap two-view probe: is there any depth between two frames?

A full pair (``reconstruction.stage``) spends most of its time on SIFT: about 200 ms of CPU
per 640x480 frame at the low contrast threshold the map needs. The fused run's 3D audit only
has to know whether a stretch of road the CNN calls clear has relief (a rut under diffuse
light is invisible to a single image). The probe answers that in about 60 ms:

1. a coarse homography from SIFT on both frames resized to ``coarse_megapixels``;
2. Shi-Tomasi corners of frame a, only where the coarse homography maps them inside b;
3. pyramidal Lucas-Kanade a -> b from the homography's guess, then b -> a; tracks whose
   forward-backward error exceeds ``max_fb_error_px`` are dropped;
4. the tracked pixels go through the same estimator chain as a full pair
   (``reconstruction.api.reconstruct_matches``: motion prior, plane homography,
   F = [x̄_k − x̄_{k−1}]× H_k, R, t, triangulation, scale α = h / d_c).

The result is an ordinary metric ``PairResult`` with about as many points as a full pair
(LK tracks are sub-pixel, so depth noise is similar), saved as
``RUN/probes/<a>_<b>_<settings>.npz`` with the ``pair_fingerprint`` of its inputs beside it.
It is not a map pair: the map and detection stages never read ``RUN/probes``.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from roadsurf.core.atomic import UNREADABLE, write_text_atomic
from roadsurf.core.camera import Camera
from roadsurf.core.errors import FrameReadError
from roadsurf.core.fingerprint import Fingerprint
from roadsurf.io.drive import Drive, read_gray
from roadsurf.io.runfolder import RunFolder, fingerprint_path, probe_filename, read_fingerprint
from roadsurf.reconstruction.api import reconstruct_matches
from roadsurf.reconstruction.config import ProbeConfig, ReconstructionConfig
from roadsurf.reconstruction.features import to_gray, track_forward_backward
from roadsurf.reconstruction.stage import pair_fingerprint
from roadsurf.reconstruction.types import PairResult, load_pair, save_pair

log = logging.getLogger(__name__)


def _coarse_homography(
    gray_a: np.ndarray, gray_b: np.ndarray, pcfg: ProbeConfig, usable: np.ndarray | None = None
) -> tuple[np.ndarray | None, str]:
    """Homography (3, 3) a -> b in full-resolution pixels from SIFT on downscaled frames, or
    (None, why). ``usable``: (H, W) bool pixels away from the camera's mask (keypoints only
    there: a burned-in stamp matches itself with no motion)."""
    scale = min(1.0, float(np.sqrt(pcfg.coarse_megapixels * 1e6 / gray_a.size)))
    if scale < 1.0:
        sa = cv2.resize(gray_a, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        sb = cv2.resize(gray_b, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    else:
        sa, sb = gray_a, gray_b
    sift = cv2.SIFT_create(nfeatures=int(pcfg.coarse_features), contrastThreshold=0.01)
    m = None
    if usable is not None:
        m = cv2.resize(usable.astype(np.uint8) * 255, (sa.shape[1], sa.shape[0]), None, 0, 0,
                       cv2.INTER_NEAREST)  # fmt: skip
    ka, da = sift.detectAndCompute(sa, m)
    kb, db = sift.detectAndCompute(sb, m)
    if da is None or db is None or len(ka) < 8 or len(kb) < 8:
        return None, f"coarse alignment: {len(ka)} and {len(kb)} keypoints"
    matches = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(da, db)
    if len(matches) < 8:
        return None, f"coarse alignment: {len(matches)} mutual matches"
    pa = (np.float32([ka[m.queryIdx].pt for m in matches]) + 0.5) / scale - 0.5
    pb = (np.float32([kb[m.trainIdx].pt for m in matches]) + 0.5) / scale - 0.5
    H, inl = cv2.findHomography(pa, pb, cv2.RANSAC, 3.0 / scale)
    if H is None or inl is None or int(inl.sum()) < 8:
        return None, "coarse alignment: no homography with 8 inliers"
    return H, ""


def probe_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    camera: Camera,
    cfg: ReconstructionConfig,
    *,
    frame_dt_s: float | None = None,
) -> PairResult:
    """Two frames ((H, W) grey or (H, W, 3) RGB) -> PairResult from tracked corners.
    frame_dt_s: as ``api.reconstruct_matches`` (a rolling shutter's frame interval).

    A frame the probe cannot use is a PairResult with status and reason, like a full pair's;
    frames of different sizes raise ValueError (``run`` turns any exception into a failed
    probe). ``timings_s`` has ``tracking`` (coarse alignment + corners + LK) besides the
    estimator's own timings.
    """
    pcfg = cfg.probe
    t0 = time.perf_counter()
    ga, gb = to_gray(image_a), to_gray(image_b)
    if ga.shape != gb.shape:
        raise ValueError(f"frames differ in size: {ga.shape} and {gb.shape}")
    # pixels whose LK window / SIFT neighbourhood stays off the camera's mask
    usable = None if camera.mask is None else camera.mask.eroded(max(pcfg.window_px // 2, 8))
    H, why = _coarse_homography(ga, gb, pcfg, usable)
    if H is None:
        return _failed(cfg, "too_few_matches", why, t0)
    h, w = ga.shape
    # corners of a whose coarse position in b is inside b, away from the border
    step = 4
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    grid = np.float32(np.c_[xs.ravel(), ys.ravel()])[:, None]
    q = cv2.perspectiveTransform(grid, H)[:, 0]
    m = pcfg.window_px // 2
    inside = (q[:, 0] >= m) & (q[:, 0] < w - m) & (q[:, 1] >= m) & (q[:, 1] < h - m)
    if usable is not None:  # in a and at their coarse position in b
        inside &= usable[ys.ravel(), xs.ravel()]
        qi = np.clip(np.rint(q).astype(int), 0, [w - 1, h - 1])
        inside &= usable[qi[:, 1], qi[:, 0]]
    mask = np.zeros((h, w), np.uint8)
    mask[ys.ravel()[inside], xs.ravel()[inside]] = 255
    mask = cv2.dilate(mask, np.ones((step + 1, step + 1), np.uint8))
    corners = cv2.goodFeaturesToTrack(
        ga,
        int(pcfg.corners),
        float(pcfg.corner_quality),
        float(pcfg.corner_spacing_px),
        mask=mask,
        blockSize=7,
    )
    if corners is None or len(corners) < cfg.min_matches:
        n = 0 if corners is None else len(corners)
        return _failed(cfg, "too_few_features", f"{n} trackable corners in the overlap", t0)
    pa = corners.astype(np.float32).reshape(-1, 1, 2)
    guess = cv2.perspectiveTransform(pa, H).astype(np.float32)
    pb, pa2, ok = track_forward_backward(
        ga, gb, pa, guess, int(pcfg.window_px), max_level=int(pcfg.pyramid_levels), iterations=30
    )
    fb = np.linalg.norm((pa2 - pa).reshape(-1, 2), axis=1)
    pa, pb = pa.reshape(-1, 2), pb.reshape(-1, 2)
    keep = ok & (fb <= pcfg.max_fb_error_px)
    keep &= (pb[:, 0] >= 0) & (pb[:, 0] <= w - 1) & (pb[:, 1] >= 0) & (pb[:, 1] <= h - 1)
    t_track = time.perf_counter() - t0
    if keep.sum() < cfg.min_matches:
        res = _failed(cfg, "too_few_matches", f"{int(keep.sum())} consistent tracks", t0)
        res.n_features_a = len(pa)
        return res
    res = reconstruct_matches(pa[keep], pb[keep], camera, cfg, frame_dt_s=frame_dt_s)
    res.n_features_a = res.n_features_b = int(len(pa))
    res.timings_s["tracking"] = t_track
    res.config_name = "probe"
    return res


def _failed(cfg: ReconstructionConfig, status: str, reason: str, t0: float) -> PairResult:
    res = PairResult("", "", -1, -1, cfg.method, status, reason)
    res.timings_s["tracking"] = time.perf_counter() - t0
    res.config_name = "probe"
    return res


def _probe_path(run_dir: Path, a: int, b: int, cfg: ReconstructionConfig) -> Path:
    # the probe settings are in the name (they are not in ``pair_fingerprint``), so probes of
    # other settings sit side by side
    digest = Fingerprint().add_repr((cfg.probe, cfg.method)).hexdigest(8)
    return RunFolder(run_dir).probes_dir / probe_filename(a, b, digest)


def run(
    cfg: ReconstructionConfig,
    drive: Drive,
    run_dir: str | Path,
    only_pairs: set[tuple[int, int]],
) -> list[PairResult]:
    """Probe the consecutive pairs (index_a, index_b) in ``only_pairs``; results in frame order.

    Each result is cached as ``RUN/probes/<a>_<b>_<settings>.npz`` (failed ones too) and reused,
    unless ``cfg.overwrite``, when the ``pair_fingerprint`` stored beside it (``.fingerprint``)
    matches the current estimator settings, camera and image files, as full pairs are. Unreadable frames give status ``unreadable_frame``. Pairs run on
    ``cfg.workers`` threads (OpenCV releases the GIL).
    """
    run_dir = Path(run_dir)
    frames = {f.index: f for f in drive.frames}
    todo = sorted(p for p in only_pairs if p[0] in frames and p[1] in frames)
    if len(todo) != len(only_pairs):
        missing = sorted(set(only_pairs) - set(todo))
        raise ValueError(f"probe pairs {missing[:5]} name frames this drive does not have")
    RunFolder(run_dir).probes_dir.mkdir(parents=True, exist_ok=True)

    def one(pair: tuple[int, int]) -> PairResult:
        fa, fb = frames[pair[0]], frames[pair[1]]
        path = _probe_path(run_dir, *pair, cfg)
        fingerprint = pair_fingerprint(cfg, drive.camera, fa, fb)
        if path.is_file() and not cfg.overwrite and read_fingerprint(path) == fingerprint:
            try:
                return load_pair(path)
            except UNREADABLE as e:
                log.warning("%s: unreadable cached probe (%s); recomputing", path, e)
        try:
            res = probe_pair(
                read_gray(fa),
                read_gray(fb),
                drive.camera,
                cfg,
                frame_dt_s=fb.timestamp_s - fa.timestamp_s,
            )
        except FrameReadError as e:
            res = PairResult("", "", -1, -1, cfg.method, "unreadable_frame", str(e))
            res.config_name = "probe"
        except Exception as e:  # noqa: BLE001 - a probe must never stop the drive run
            log.exception("probe %s -> %s failed unexpectedly", fa.filename, fb.filename)
            reason = f"unexpected {type(e).__name__}: {e}"
            res = PairResult("", "", -1, -1, cfg.method, "geometry_failed", reason)
            res.config_name = "probe"
        res.frame_a, res.frame_b, res.index_a, res.index_b = (
            fa.filename,
            fb.filename,
            fa.index,
            fb.index,
        )
        # the old fingerprint goes first: a probe never sits beside another's fingerprint
        fingerprint_path(path).unlink(missing_ok=True)
        save_pair(path, res)
        write_text_atomic(fingerprint_path(path), fingerprint + "\n")
        return res

    if not todo:
        return []
    workers = max(1, int(cfg.workers))
    bar = tqdm(total=len(todo), desc="3D probes", unit="pair", leave=False)
    out: list[PairResult] = []
    if workers == 1:
        for p in todo:
            out.append(one(p))
            bar.update()
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for res in pool.map(one, todo):
                out.append(res)
                bar.update()
    bar.close()
    n_ok = sum(r.ok for r in out)
    log.info("3D probes: %d pair(s), %d ok", len(out), n_ok)
    return out
