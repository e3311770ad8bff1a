"""Feature detection (SIFT default, ORB, AKAZE) and mutual nearest-neighbour + ratio matching.

Keypoints are stored raw (as detected); ``Camera.undistort_px`` maps them to the ideal pinhole
before any geometry when the camera has distortion.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from roadsurf.core.atomic import write_npz_atomic
from roadsurf.core.camera import capped_scale
from roadsurf.core.errors import ConfigError
from roadsurf.core.imagemask import ImageMask
from roadsurf.reconstruction.config import FeatureConfig
from roadsurf.reconstruction.types import Features


def _detector(cfg: FeatureConfig, n: int) -> cv2.Feature2D:
    if cfg.kind == "sift":
        return cv2.SIFT_create(
            nfeatures=n,
            nOctaveLayers=int(cfg.n_octave_layers),
            contrastThreshold=float(cfg.contrast_threshold),
        )
    if cfg.kind == "orb":
        return cv2.ORB_create(nfeatures=n if n > 0 else 20_000, fastThreshold=5)
    if cfg.kind == "akaze":
        return cv2.AKAZE_create(threshold=1e-4)  # type: ignore[attr-defined]
    raise ConfigError(f"features.kind={cfg.kind!r}: use sift, orb or akaze")


def check_available(cfg: FeatureConfig) -> None:
    """Raise ConfigError before a run when this OpenCV build lacks the chosen detector."""
    if cfg.kind == "akaze" and not hasattr(cv2, "AKAZE_create"):
        raise ConfigError(
            f"features.kind='akaze' is not available in OpenCV {cv2.__version__} "
            "(AKAZE left the main modules in OpenCV 5); use 'sift' or 'orb', or install an "
            "OpenCV build with AKAZE"
        )
    if cfg.kind not in ("sift", "orb", "akaze"):
        raise ConfigError(f"features.kind={cfg.kind!r}: use sift, orb or akaze")


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) RGB image -> uint8 greyscale (H, W)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def detect(image: np.ndarray, cfg: FeatureConfig, mask: ImageMask | None = None) -> Features:
    """Detect and describe keypoints of one image, at most cfg.max_features, spread on a grid.
    ``mask`` (the camera's, raw pixels of ``image``): the masked pixels are filled with the
    median grey first (a descriptor reaching over the mask's edge sees flat ground, not a
    black stamp), and keypoints within their own size (the diameter OpenCV gives) of a masked
    pixel are dropped before the spread."""
    check_available(cfg)
    gray = to_gray(image)
    if mask is not None:
        gray = mask.fill(gray)
    scale = capped_scale(cfg.downscale, gray.shape[1], gray.shape[0], cfg.max_detect_megapixels)
    if 0 < scale < 1:
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    if cfg.clahe_clip > 0:  # even out shadows / dark pothole floors for the detector only
        tiles = max(1, int(cfg.clahe_tiles))
        gray = cv2.createCLAHE(cfg.clahe_clip, (tiles, tiles)).apply(gray)
    pad = max(0, int(cfg.border_pad_px))
    h0, w0 = gray.shape[:2]
    if pad:
        gray = cv2.copyMakeBorder(gray, pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
    cap = cfg.max_features
    if cfg.grid_cells > 0:
        cap = int(round(cfg.candidates_per_feature * cfg.max_features))
    det = _detector(cfg, cap)
    # Detect all candidates, keep an even spread, and describe only those: the descriptors,
    # not the detection, dominate SIFT's cost (~30 us per keypoint).
    kps = list(det.detect(gray, None) or [])
    if pad:  # keypoints in the mirrored border are not real
        kps = [k for k in kps if pad <= k.pt[0] <= pad + w0 - 1 and pad <= k.pt[1] <= pad + h0 - 1]
    if not kps:
        return _empty(cfg)
    pts = np.array([k.pt for k in kps], dtype=np.float32) - pad
    if mask is not None:
        s = scale if 0 < scale < 1 else 1.0
        radius = np.array([k.size for k in kps]) / s
        ok = mask.usable_at((pts.astype(np.float64) + 0.5) / s - 0.5, radius)
        kps, pts = [k for k, o in zip(kps, ok, strict=True) if o], pts[ok]
        if not kps:
            return _empty(cfg)
    resp = np.array([k.response for k in kps], dtype=np.float32)
    keep = _spread(pts, resp, (h0, w0), cfg)
    kps, desc = det.compute(gray, [kps[i] for i in keep])
    if desc is None or len(kps) == 0:
        return _empty(cfg)
    pts = np.array([k.pt for k in kps], dtype=np.float32) - pad
    if 0 < scale < 1:
        pts = (pts + 0.5) / scale - 0.5
    return Features(pts.astype(np.float32), desc, cfg.kind)


def detect_stretched(
    image: np.ndarray, cfg: FeatureConfig, scale_v: float, mask: ImageMask | None = None
) -> Features:
    """Features of ``image`` resized vertically by ``scale_v`` (0 < scale_v <= 1), detected and
    described there (an affine view simulation as in ASIFT) and returned at the pixel positions
    of the image as recorded (u right, v down), so everything after matching is unchanged."""
    if not 0 < scale_v <= 1:
        raise ValueError(f"vertical scale {scale_v} outside (0, 1]")
    gray = to_gray(image)
    if scale_v == 1:
        return detect(gray, cfg, mask)
    h = max(1, int(round(gray.shape[0] * scale_v)))
    small = None
    if mask is not None:  # the mask squeezed the same way (a pixel masked if any of it is)
        sq = cv2.resize(
            mask.usable.astype(np.float32), (gray.shape[1], h), interpolation=cv2.INTER_AREA
        )
        small = ImageMask(sq > 0.999, mask.source)
    f = detect(cv2.resize(gray, (gray.shape[1], h), interpolation=cv2.INTER_AREA), cfg, small)
    pts = f.keypoints_px.astype(np.float64)
    pts[:, 1] = (pts[:, 1] + 0.5) * (gray.shape[0] / h) - 0.5  # pixel centres, not corners
    return Features(pts.astype(np.float32), f.descriptors, f.kind)


def _empty(cfg: FeatureConfig) -> Features:
    return Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), cfg.kind)


def _spread(
    pts: np.ndarray, resp: np.ndarray, shape: tuple[int, ...], cfg: FeatureConfig
) -> np.ndarray:
    """Indices of the strongest keypoints with an equal quota per grid cell (even coverage)."""
    n = cfg.max_features
    if cfg.grid_cells <= 0 or len(pts) <= n:
        return np.argsort(-resp)[:n]
    g = cfg.grid_cells
    cell = (
        np.minimum(pts[:, 1] * g // shape[0], g - 1) * g
        + np.minimum(pts[:, 0] * g // shape[1], g - 1)
    ).astype(int)
    order = np.lexsort((-resp, cell))
    rank = np.empty(len(pts), dtype=int)
    cs = cell[order]
    starts = np.r_[0, np.flatnonzero(np.diff(cs)) + 1]
    counts = np.diff(np.r_[starts, len(cs)])
    rank[order] = np.arange(len(cs)) - np.repeat(starts, counts)
    # Smallest rank first (round-robin across cells), then by response.
    return np.lexsort((-resp, rank))[:n]


def match(fa: Features, fb: Features, cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours with Lowe's ratio test -> (idx_a, idx_b) int arrays."""
    if len(fa.keypoints_px) < 2 or len(fb.keypoints_px) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    binary = fa.descriptors.dtype == np.uint8
    da, db = fa.descriptors, fb.descriptors
    if binary or cfg.matcher == "bf":
        bf = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2)
    else:
        cv2.setRNGSeed(0)  # FLANN's randomised trees: same matches on every run
        bf = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": int(cfg.flann_checks)})
        da = np.ascontiguousarray(da, dtype=np.float32)
        db = np.ascontiguousarray(db, dtype=np.float32)
    knn = bf.knnMatch(da, db, k=2)
    pairs = [
        (m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in knn if len(m) >= 2
    ]
    if not pairs:
        return np.zeros(0, int), np.zeros(0, int)
    arr = np.array(pairs, dtype=np.float64)
    ia_a, ib_a = arr[:, 0].astype(int), arr[:, 1].astype(int)
    keep = arr[:, 2] < cfg.ratio * arr[:, 3]
    if cfg.mutual and keep.any():
        # the way back only for b's features that a kept match ends on (a fifth to a third of
        # b's): each query's nearest neighbour is the same as in a search of all of b's
        jb = np.unique(ib_a[keep])
        back = bf.match(np.ascontiguousarray(db[jb]), da)
        best_a = np.full(len(db), -1, int)
        for m in back:
            best_a[jb[m.queryIdx]] = m.trainIdx
        keep &= best_a[ib_a] == ia_a
    return ia_a[keep], ib_a[keep]


def track_forward_backward(
    a8: np.ndarray,
    b8: np.ndarray,
    ra: np.ndarray,
    rb0: np.ndarray,
    window_px: int,
    *,
    max_level: int,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade a -> b from the initial guesses ``rb0``, then b -> a back.

    a8, b8: (H, W) uint8 images; ra, rb0: (N, 1, 2) float32 raw pixels. Returns (rb, ra2, ok):
    the tracked pixels in b, the back-tracked pixels in a (both (N, 1, 2)) and (N,) bool, both
    directions converged (the caller judges the forward-backward error against its spread).
    """
    lk = {
        "winSize": (window_px, window_px),
        "maxLevel": max_level,
        "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 0.01),
        "minEigThreshold": 1e-4,
        "flags": cv2.OPTFLOW_USE_INITIAL_FLOW,
    }
    rb, st, _ = cv2.calcOpticalFlowPyrLK(a8, b8, ra, rb0.copy(), **lk)
    ra2, st2, _ = cv2.calcOpticalFlowPyrLK(b8, a8, rb, ra.copy(), **lk)
    return rb, ra2, (st.ravel() == 1) & (st2.ravel() == 1)


def save_features(path: str | Path, f: Features) -> Path:
    """Cache ``f`` as an uncompressed .npz; ``load_features`` gives it back bit for bit.

    OpenCV's SIFT descriptors are float32 holding whole numbers 0-255: they are stored as
    uint8 (lossless) with their dtype. zlib on the float32 descriptors took ~130 ms a frame,
    about as long as detecting them; the uint8 file is also smaller (~0.34 against 0.43 MB).
    """
    d = np.asarray(f.descriptors)
    store = d
    if d.dtype.kind == "f" and d.size and _whole_bytes(d):
        store = d.astype(np.uint8)
    return write_npz_atomic(
        path,
        compressed=False,
        keypoints_px=f.keypoints_px,
        descriptors=store,
        descriptor_dtype=np.asarray(str(d.dtype)),
        kind=np.asarray(f.kind),
    )


def _whole_bytes(a: np.ndarray) -> bool:
    """Every value a whole number in 0..255 (exactly representable as uint8)."""
    return bool(np.all(a >= 0) and np.all(a <= 255) and np.array_equal(a, np.floor(a)))


def load_features(path: str | Path) -> Features:
    """Features saved by ``save_features`` (also the older zlib files with float descriptors)."""
    with np.load(path, allow_pickle=False) as z:
        d = z["descriptors"]
        if "descriptor_dtype" in z.files:
            d = d.astype(str(z["descriptor_dtype"]), copy=False)
        return Features(z["keypoints_px"], d, str(z["kind"]))
