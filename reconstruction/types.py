"""Artifacts exchanged by the reconstruction stage.

A ``PairResult`` is saved per consecutive frame pair as ``RUN/pairs/<a>_<b>.npz`` (see
``save_pair`` / ``load_pair``) and read by mapping, detection and the viewer.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import write_npz_atomic

# Status values. "ok" is the only success; everything else is a reported failure, never raised.
STATUS_OK = "ok"
# the camera did not move between the frames (a stopped vehicle): no depth, but the pose graph
# holds the two frames together (mapping.pose_graph) instead of bridging a gap
STATUS_NO_MOTION = "no_motion"
STATUS_FAILED = (
    "unreadable_frame",
    "too_few_features",
    "too_few_matches",
    "no_overlap",
    "not_near_planar",
    "geometry_failed",
    "scale_failed",
    STATUS_NO_MOTION,
)


class PairFailure(Exception):
    """Internal to the estimators: a pair cannot be reconstructed. ``estimate_matches`` turns it
    into the pair's status and reason; it never leaves that function."""

    def __init__(self, status: str, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


@dataclass
class Features:
    """Keypoints and descriptors of one frame, computed once and reused by both its pairs."""

    keypoints_px: (
        np.ndarray
    )  # (N, 2) float32 pixel positions (u right, v down), undistorted? no: raw
    descriptors: np.ndarray  # (N, D) float32 (SIFT) or uint8 (ORB/AKAZE)
    kind: str  # "sift" | "orb" | "akaze"


@dataclass
class PairResult:
    """Metric two-view reconstruction of frames a -> b (all lengths in metres)."""

    frame_a: str  # filename of the first frame
    frame_b: str  # filename of the second frame
    index_a: int  # Frame.index of a
    index_b: int  # Frame.index of b
    method: str  # "proposed" | "rotation_aware" | "classic" | "colmap" | "stereo"
    status: str  # STATUS_OK or one of STATUS_FAILED
    reason: str = ""  # human-readable explanation when status != ok
    points_cam_a_m: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 3))
    )  # (N, 3) in camera a
    px_a: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (N, 2) pixels in image a
    px_b: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (N, 2) pixels in image b
    cov_m2: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 3, 3))
    )  # (N, 3, 3) covariance, m^2
    plane_dist_m: np.ndarray = field(
        default_factory=lambda: np.zeros(0)
    )  # (N,) signed, negative below road
    plane: np.ndarray = field(
        default_factory=lambda: np.full(3, np.nan)
    )  # (p0, p1, p2): Z = p0 X + p1 Y + p2 (m)
    R_b_from_a: np.ndarray = field(default_factory=lambda: np.eye(3))  # X_b = R X_a + t
    t_b_from_a_m: np.ndarray = field(default_factory=lambda: np.zeros(3))  # metric translation (m)
    H: np.ndarray = field(
        default_factory=lambda: np.full((3, 3), np.nan)
    )  # road-plane homography a -> b (px)
    F: np.ndarray = field(
        default_factory=lambda: np.full((3, 3), np.nan)
    )  # fundamental matrix, x_b^T F x_a = 0
    scale_alpha: float = float("nan")  # α = h / d_c
    n_features_a: int = 0
    n_features_b: int = 0
    n_matches: int = 0  # after mutual NN + ratio test
    n_prior_inliers: int = 0  # after the motion-prior rejection (λ)
    n_inliers: int = 0  # after RANSAC / final geometry
    outlier_ratio_h: float = float("nan")  # homography RANSAC outlier share (near-planar test)
    rejected_px_a: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 2))
    )  # mismatches (for the viewer)
    rejected_px_b: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    timings_s: dict[str, float] = field(default_factory=dict)
    match_idx: np.ndarray = field(
        default_factory=lambda: np.zeros(0, dtype=np.int64)
    )  # (N,) index of each point into the input match list (reconstruct_matches order)
    stretch_b: float = 1.0  # vertical scale of image b its features were detected at (unitless;
    # 1 = as recorded, < 1 = the stretch retry, ``FeatureConfig.stretch_retry``)
    config_name: str = ""  # estimator detail, e.g. pycolmap's configuration (PLANAR, CALIBRATED)

    @property
    def ok(self) -> bool:
        return self.status == STATUS_OK

    @property
    def n_points(self) -> int:
        return int(self.points_cam_a_m.shape[0])

    @property
    def cam_b_from_cam_a(self) -> np.ndarray:
        """4x4 rigid transform X_b = T X_a (metres)."""
        T = np.eye(4)
        T[:3, :3] = self.R_b_from_a
        T[:3, 3] = self.t_b_from_a_m
        return T


# Fields nothing after the reconstruction reads in a drive run (the viewer and the studies load
# pairs from RUN/pairs): ``stored`` keeps them on disk only. They are over half of a pair's
# memory (the 3x3 covariance of every point), and a drive's pairs stay in memory to the end of
# the run (issue 31 #10: memory flat in the drive's length).
ON_DISK_FIELDS = ("cov_m2", "match_idx")


class StoredPairResult(PairResult):
    """A ``PairResult`` saved at ``npz`` (``save_pair``) whose ``ON_DISK_FIELDS`` are read from
    that file on each access instead of being kept in memory; every other attribute is held as
    usual, and assigning a field holds that value from then on. Made by ``stored``."""

    _npz: Path

    def __getattr__(self, name: str) -> Any:
        # only called for attributes not held: the fields left on disk
        npz = self.__dict__.get("_npz")
        if name not in ON_DISK_FIELDS or npz is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        with np.load(npz, allow_pickle=False) as z:
            if name in z.files:
                return z[name]
        return PairResult.__dataclass_fields__[name].default_factory()  # type: ignore[misc]


def stored(res: PairResult, npz: str | Path) -> PairResult:
    """``res``, just saved at ``npz`` by ``save_pair``, as a ``StoredPairResult`` (the same
    values; ``ON_DISK_FIELDS`` read back from the file when used)."""
    out = StoredPairResult.__new__(StoredPairResult)
    out.__dict__.update({k: v for k, v in res.__dict__.items() if k not in ON_DISK_FIELDS})
    out.__dict__["_npz"] = Path(npz)
    return out


def save_pair(path: str | Path, res: PairResult) -> Path:
    """Write a PairResult atomically as .npz (arrays as arrays, scalars/strings as 0-d arrays)."""
    data: dict[str, np.ndarray] = {}
    for f in fields(PairResult):
        v = getattr(res, f.name)
        if f.name == "timings_s":
            data["timings_keys"] = np.array(list(v.keys()), dtype=str)
            data["timings_vals"] = np.array(list(v.values()), dtype=float)
        else:
            data[f.name] = np.asarray(v)
    return write_npz_atomic(path, **data)


def load_pair(path: str | Path) -> PairResult:
    with np.load(path, allow_pickle=False) as z:
        kw: dict[str, Any] = {}
        for f in fields(PairResult):
            if f.name == "timings_s":
                kw[f.name] = dict(
                    zip(z["timings_keys"].tolist(), z["timings_vals"].tolist(), strict=True)
                )
                continue
            if f.name not in z.files:  # written before an additive field existed
                continue
            v = z[f.name]
            if v.ndim == 0:
                v = v.item()
            kw[f.name] = v
    return PairResult(**kw)
