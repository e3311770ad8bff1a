"""The global cloud: every ok pair's metric points posed in ENU and coloured from their
image, height seams between pair patches removed (a strip adjustment), then fused in a voxel
hash."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from roadsurf.core.errors import FrameReadError
from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.io.drive import Drive, Frame, read_image
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.surface import LocalSurface
from roadsurf.mapping.types import Trajectory

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


def collect_points(
    cfg: MappingConfig,
    drive: Drive,
    pairs: list[PairResult],
    traj: Trajectory,
    frames_by_index: dict[int, Frame],
    pose_of: dict[str, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    xs, cs, fs = [], [], []
    ok = [p for p in pairs if p.ok and p.n_points > 0 and p.frame_a in pose_of]
    for p in tqdm(ok, desc="map points", unit="pair", leave=False):
        P = np.asarray(p.points_cam_a_m, float)
        good = np.all(np.isfinite(P), axis=1) & (P[:, 2] > 0) & (P[:, 2] < cfg.max_point_depth_m)
        if not good.any():
            continue
        P = P[good]
        W = traj.world_from_cam[pose_of[p.frame_a]]
        xs.append(P @ W[:3, :3].T + W[:3, 3])
        col = np.full((len(P), 3), 128, np.uint8)
        fr = frames_by_index.get(int(p.index_a))
        if cfg.colour_from_images and fr is not None:
            try:
                img = read_image(fr)
                # the pair's pixels are ideal (undistorted); the image is as recorded
                px = drive.camera.distort_px(np.asarray(p.px_a, float)[good])
                u = np.clip(np.round(px[:, 0]).astype(int), 0, img.shape[1] - 1)
                v = np.clip(np.round(px[:, 1]).astype(int), 0, img.shape[0] - 1)
                col = img[v, u]
            except (FrameReadError, OSError) as e:
                log.warning("globalmap: no colour for %s (%s)", fr.filename, e)
        cs.append(col)
        fs.append(np.full(len(P), int(p.index_a), np.int64))
    if not xs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int64), 0
    xyz = np.concatenate(xs)
    return xyz, np.concatenate(cs), np.concatenate(fs), len(xyz)


def align_patches(
    cfg: MappingConfig, xyz: np.ndarray, patch: np.ndarray, iterations: int = 4
) -> tuple[np.ndarray, dict[str, float]]:
    """Remove height seams between pair patches (a strip adjustment).

    Each point is compared with its nearest neighbours (within 2 cm) from OTHER patches, using
    residuals to the local road surface so that the road slope cancels. Each patch then gets a
    robust planar correction (offset + tilt; defect mismatches trimmed by MAD) of half the
    disagreement, so neighbouring patches meet in the middle (Jacobi iterations).
    Returns the corrected (N, 3) points and statistics of the applied offsets (m)."""
    from scipy.spatial import cKDTree

    xyz = xyz.copy()
    ids, inv = np.unique(patch, return_inverse=True)
    applied = np.zeros(len(ids))
    order = np.argsort(inv, kind="stable")
    bounds = np.searchsorted(inv[order], np.arange(len(ids) + 1))
    tree = cKDTree(xyz[:, :2])
    dist, nb = tree.query(xyz[:, :2], k=8, distance_upper_bound=0.02)
    valid_nb = np.isfinite(dist)
    del dist, tree  # (N, 8) float64 and the tree: not needed any more (memory, issue 31 #10)
    nb[~valid_nb] = 0  # in place: no second (N, 8) array
    other = valid_nb & (inv[nb] != inv[:, None])
    del valid_nb
    for _ in range(iterations):
        surf = LocalSurface(cfg, xyz, progress=False)
        r = surf.residual(xyz)
        rn = r[nb]
        rn[~other] = np.nan  # in place: one (N, 8) array, not two
        with np.errstate(all="ignore"):
            cnt = np.sum(np.isfinite(rn), axis=1)
            ref = np.where(cnt > 0, np.nansum(rn, axis=1) / np.maximum(cnt, 1), np.nan)
        d = r - ref  # this point's height minus its neighbours' from other patches
        corr_all = np.zeros(len(xyz))
        for j in range(len(ids)):
            sel = order[bounds[j] : bounds[j + 1]]
            dd = d[sel]
            ok = np.isfinite(dd)
            if ok.sum() < 15:
                continue
            P = xyz[sel]
            c = P[ok, :2].mean(0)
            A = np.column_stack([np.ones(len(P)), P[:, 0] - c[0], P[:, 1] - c[1]])
            inl = ok.copy()
            coef = np.zeros(3)
            for _k in range(4):
                coef, *_ = np.linalg.lstsq(A[inl], dd[inl], rcond=None)
                e = np.where(ok, dd - A @ coef, np.inf)
                s = MAD_TO_SIGMA * np.median(np.abs(e[inl])) + 1e-6
                new = np.abs(e) < max(3 * s, 0.5 * cfg.local_fit_inlier_m)
                if new.sum() < 10 or np.array_equal(new, inl):
                    break
                inl = new
            if inl.sum() < 30:
                coef[1:] = 0.0  # too little overlap to estimate a tilt
            corr_all[sel] = 0.5 * (A @ coef)
            applied[j] += 0.5 * coef[0]
        xyz[:, 2] -= corr_all
    stats = {
        "patches": int(len(ids)),
        "offset_abs_median_m": float(np.median(np.abs(applied))) if len(ids) else 0.0,
        "offset_abs_max_m": float(np.max(np.abs(applied))) if len(ids) else 0.0,
    }
    return xyz, stats


def voxel_fuse(
    xyz: np.ndarray, rgb: np.ndarray, frame_idx: np.ndarray, voxel_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fuse points in the same voxel (numpy hash): mean xyz and colour, first frame index, and
    the observation count. Returns (xyz (M,3), rgb (M,3) uint8, frame (M,), n_obs (M,)).

    Not open3d: its voxel_down_sample_and_trace gives the same arrays 11-22x slower (its trace
    is a Python list per voxel; benchmarks/voxel_fuse.py, docs/mapping.md "Libraries")."""
    if len(xyz) == 0 or voxel_m <= 0:
        return xyz, rgb, frame_idx, np.ones(len(xyz), np.int64)
    q = np.floor((xyz - xyz.min(0)) / voxel_m).astype(np.int64)
    dims = q.max(0) + 1
    key = (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    m = len(cnt)
    out = np.zeros((m, 3))
    col = np.zeros((m, 3))
    for j in range(3):
        out[:, j] = np.bincount(inv, weights=xyz[:, j], minlength=m) / cnt
        col[:, j] = np.bincount(inv, weights=rgb[:, j].astype(float), minlength=m) / cnt
    first = np.full(m, np.iinfo(np.int64).max)
    np.minimum.at(first, inv, frame_idx)
    return out, np.clip(np.round(col), 0, 255).astype(np.uint8), first, cnt.astype(np.int64)
