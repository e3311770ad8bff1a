"""Scale, level and place each COLMAP model (steps 2-3 of the SfM baseline).

Scale, per model (dissertation eq. 3.31-3.34, applied per camera): for every registered image a
robust plane is fitted to the 3D points it sees; d_c is the median camera-to-plane distance and
α = h / d_c with h = camera.yaml ``height_m``. The vertical is the mean plane normal. Poses that
disagree with their neighbours (heading jump > 20°, camera-to-road distance > 25% off) are
dropped with a reason (the planar two-fold ambiguity shows up so).

Georeferencing, per model: with GPS, a robust 2D rigid (or similarity) fit of the levelled,
scaled camera centres to the GPS ENU positions interpolated at the frame times (frames far off a
good fit are dropped as bad poses); the vertical offset, and an along-track tilt when the GPS
altitude is good enough to show one, from the GPS altitude. The largest model is used first,
then every smaller model that the GPS can place adds the frames the larger ones lack. Without
GPS: only the largest model, in a local metric frame (first camera at the origin, its forward
direction along +y).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA, fit_plane_ransac
from roadsurf.core.geometry import (
    EnuReference,
    heading_deg_from_world_rotation,
    rotation_b_from_a,
    rotation_from_euler_xyz,
)
from roadsurf.io.drive import Drive, Frame
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.pose_gps import GpsFixes, gps_at, gps_enu
from roadsurf.mapping.types import PoseReport
from roadsurf.pipeline.sfm.config import SfmBaselineConfig
from roadsurf.pipeline.sfm.fits import robust_fit_2d

if TYPE_CHECKING:
    import pycolmap

log = logging.getLogger(__name__)


def drive_gps(drive: Drive) -> tuple[EnuReference | None, GpsFixes | None]:
    """The ENU origin and the GPS fixes in it, chosen as the pose fusion chooses them
    (``mapping.pose_gps.gps_enu``: the fix nearest the middle frame, its altitude or the
    nearest finite one; fixes within its default margin of the frame times). (None, None)
    without 2 such fixes; a drive without GPS gets a warning for the report."""
    if drive.gps is None:
        drive.warnings.append("no GPS: outputs are in a local metric frame (crs null)")
        return None, None
    if len(drive.gps) < 2 or not drive.frames:
        return None, None
    t = np.array([f.timestamp_s for f in drive.frames])
    ref, gps = gps_enu(MappingConfig(), drive, t, PoseReport())
    if ref is None or gps is None or len(gps.t_s) < 2:
        return None, None
    return ref, gps


def place_models(
    models: dict[int, pycolmap.Reconstruction],
    sizes: dict[int, int],
    drive: Drive,
    cfg: SfmBaselineConfig,
    ref: EnuReference | None,
    gps: GpsFixes | None,
) -> tuple[list[ModelGeo], dict[int, str], dict[str, str], EnuReference | None]:
    """Georeference the models (``sizes``: registered images per model), largest first, on the
    GPS fixes ``gps`` (ENU about ``ref``; both None without GPS).
    Returns (the models used, a note per model not used, filename -> why its pose was dropped,
    the reference: None when the outputs end up in a local frame)."""
    order = sorted(sizes, key=lambda k: (-sizes[k], k))  # largest model first
    claimed: set[str] = set()
    parts: list[ModelGeo] = []
    notes: dict[int, str] = {}
    outlier_reasons: dict[str, str] = {}
    for k in order:
        if sizes[k] < 2:
            notes[k] = "the model has fewer than 2 images"
            continue
        if parts and ref is None:
            notes[k] = "without GPS only the largest model can be placed (local frame)"
            continue
        try:
            geo = georeference_model(
                k, models[k], drive, cfg, gps if ref is not None else None, claimed
            )
        except ModelRejected as e:
            notes[k] = str(e)
            log.info("model %d (%d images) not used: %s", k, sizes[k], e)
            continue
        if ref is not None and not parts and geo.align.get("kind") == "none":
            ref = None  # GPS does not overlap the main model: local frame for everything
        outlier_reasons.update(geo.outliers)
        claimed.update(f.filename for f in geo.frames)
        parts.append(geo)
        if ref is None:
            break
    return parts, notes, outlier_reasons, ref


def _gps_at_frames(gps: GpsFixes, times: np.ndarray, max_gap_s: float) -> np.ndarray:
    """GPS ENU (N, 3) at ``times`` (``mapping.pose_gps.gps_at``: linear between fixes); NaN rows
    where no fix is near: more than ``max_gap_s`` outside the log, or inside a gap longer than
    2 ``max_gap_s`` and more than ``max_gap_s`` from both its fixes."""
    ts = gps.t_s
    out = np.array([gps_at(gps, float(t)) for t in times]).reshape(-1, 3)
    j = np.clip(np.searchsorted(ts, times), 1, len(ts) - 1)
    gap = np.minimum(np.abs(times - ts[j - 1]), np.abs(ts[j] - times))
    bad = (times < ts[0] - max_gap_s) | (times > ts[-1] + max_gap_s)
    bad |= (gap > max_gap_s) & (ts[j] - ts[j - 1] > 2 * max_gap_s)
    out[bad] = np.nan
    return out


class ModelRejected(Exception):
    """A COLMAP model that cannot be scaled or placed (the reason goes to the report)."""


@dataclass
class ModelGeo:
    """One COLMAP model, scaled and placed in the ENU (or local) frame."""

    index: int
    frames: list[Frame]  # Frames this model provides to the outputs (capture order)
    R_wc: np.ndarray  # (M, 3, 3) world_from_cam rotations
    c_w: np.ndarray  # (M, 3) camera centres (m)
    p_w: np.ndarray  # (K, 3) points (m)
    rgb: np.ndarray  # (K, 3) uint8
    scale: dict[str, Any]
    align: dict[str, Any]
    outliers: dict[str, str]  # filename -> why its pose was rejected


def _fit_vertical_tilt(
    c_h: np.ndarray, gps_enu: np.ndarray, ok: np.ndarray, cfg: SfmBaselineConfig
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Small rotation about the horizontal cross-track axis that makes the camera heights follow
    the GPS altitude along the track: dz = a + g·s (s = along-track metres), fitted robustly.
    (The cross-track tilt is unobservable from a near-straight track; it stays from the road
    normal.) Used only when it explains the altitudes clearly better than a constant offset
    and stays under ``gps_tilt_max_deg``; consumer GPS altitude is too noisy to pass.
    Returns (R (3, 3), pivot (3,), tilt degrees) or None."""
    if not cfg.gps_tilt_correction or ok.sum() < 5:
        return None
    xy = c_h[ok, :2]
    dz = gps_enu[ok, 2] - c_h[ok, 2]
    pivot = np.array([*xy.mean(axis=0), float(c_h[ok, 2].mean())])
    _, _, vt = np.linalg.svd(xy - pivot[:2], full_matrices=False)
    u = vt[0]  # along-track direction
    s_m = (xy - pivot[:2]) @ u
    if np.ptp(s_m) < 2.0:
        return None
    A = np.column_stack([np.ones_like(s_m), s_m])
    w = np.ones(len(s_m), bool)
    coef = np.zeros(2)
    for _ in range(4):
        coef, *_ = np.linalg.lstsq(A[w], dz[w], rcond=None)
        r = dz - A @ coef
        sig = MAD_TO_SIGMA * float(np.median(np.abs(r[w]))) + 1e-6
        new = np.abs(r) <= 3 * sig
        if new.sum() < 5 or np.array_equal(new, w):
            break
        w = new
    rms_tilt = float(np.sqrt(np.mean((dz - A @ coef)[w] ** 2)))
    rms_flat = float(np.sqrt(np.mean((dz - np.median(dz))[w] ** 2)))
    b, c = float(coef[1] * u[0]), float(coef[1] * u[1])
    tilt_deg = math.degrees(math.atan(abs(float(coef[1]))))
    if tilt_deg > cfg.gps_tilt_max_deg or rms_tilt > 0.5 * rms_flat:
        return None
    n_new = np.array([-b, -c, 1.0])
    R = rotation_b_from_a(np.array([0.0, 0.0, 1.0]), n_new / np.linalg.norm(n_new))
    return R, pivot, tilt_deg


def _neighbour_heading_dev(head_deg: np.ndarray, k: int = 3) -> np.ndarray:
    """|heading - median heading of the k neighbours on each side| (degrees, (N,))."""
    n = len(head_deg)
    dev = np.zeros(n)
    for i in range(n):
        nb = [j for j in range(max(0, i - k), min(n, i + k + 1)) if j != i]
        if not nb:
            continue
        d = (head_deg[nb] - head_deg[i] + 180.0) % 360.0 - 180.0
        dev[i] = abs(float(np.median(d)))
    return dev


def georeference_model(
    k: int,
    rec: pycolmap.Reconstruction,
    drive: Drive,
    cfg: SfmBaselineConfig,
    gps: GpsFixes | None,
    claimed: set[str],
) -> ModelGeo:
    """Scale one COLMAP model by the camera height (α = h / d_c), level it with the road
    normal, drop inconsistent poses, and place it on the GPS (2D fit) or in a local frame."""
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    reg = [f for f in drive.frames if f.filename in by_name]
    # COLMAP camera axes = ours (x right, y down the image, z along the optical axis)
    cam_from_world = np.stack([by_name[f.filename].cam_from_world().matrix() for f in reg])
    R_cw = cam_from_world[:, :, :3]
    centres = np.einsum("nji,nj->ni", R_cw, -cam_from_world[:, :, 3])

    pids = np.array(list(rec.points3D.keys()), dtype=np.int64)
    pts = np.array([rec.points3D[p].xyz for p in pids]).reshape(-1, 3)
    rgb = np.array([rec.points3D[p].color for p in pids], dtype=np.uint8).reshape(-1, 3)
    pid_row = {int(p): i for i, p in enumerate(pids)}
    img_id_name = {im.image_id: im.name for im in by_name.values()}

    # ---- per-image robust plane: d_c (model units) and the up direction (eq. 3.31-3.33)
    rng = np.random.default_rng(cfg.seed)
    d_c = np.full(len(reg), np.nan)
    normals = np.full((len(reg), 3), np.nan)
    plane_inl = []
    for i, f in enumerate(reg):
        rows = [pid_row[int(p.point3D_id)] for p in by_name[f.filename].points2D if p.has_point3D()]
        if len(rows) < cfg.min_plane_points:
            continue
        P = pts[rows]
        thr = cfg.plane_inlier_rel * float(np.median(np.linalg.norm(P - centres[i], axis=1)))
        n, d, inl = fit_plane_ransac(P, thr, cfg.plane_iterations, rng)
        dist = float(n @ centres[i] + d)
        if dist < 0:  # orient the normal from the road towards the camera (= up)
            n, dist = -n, -dist
        d_c[i], normals[i] = dist, n
        plane_inl.append(float(inl.mean()))
    has = np.isfinite(d_c)
    if not has.any():
        raise ModelRejected(f"no image sees {cfg.min_plane_points} 3D points: no road plane")
    d_c_med = float(np.median(d_c[has]))
    alpha = drive.camera.height_m / d_c_med  # eq. 3.34
    up = np.nanmean(normals[has], axis=0)
    up /= np.linalg.norm(up)
    R_level = rotation_b_from_a(up, np.array([0.0, 0.0, 1.0]))
    origin = centres[0]
    c_lv = alpha * (centres - origin) @ R_level.T
    p_lv = alpha * (pts - origin) @ R_level.T
    R_wc_lv = np.einsum("ij,nkj->nik", R_level, R_cw)  # R_level @ R_cw.T

    # ---- pose outliers: a flipped/ambiguous planar pose shows as a heading jump against its
    # neighbours or a camera-to-road distance far from the others
    head = np.array([heading_deg_from_world_rotation(R) for R in R_wc_lv])
    bad = _neighbour_heading_dev(head) > 20.0
    bad |= has & (np.abs(d_c / d_c_med - 1.0) > 0.25)
    outliers = {
        f.filename: (
            f"registered by COLMAP (sparse/{k}) but its pose is inconsistent: heading "
            f"{_neighbour_heading_dev(head)[i]:.0f}° off its neighbours, camera-to-road "
            f"distance {alpha * d_c[i]:.2f} m vs h = {drive.camera.height_m} m; dropped"
        )
        for i, f in enumerate(reg)
        if bad[i]
    }
    good = ~bad
    if good.sum() < 2:
        raise ModelRejected("fewer than 2 consistent poses")

    scale = {
        "height_m": drive.camera.height_m,
        "d_c_model_median": d_c_med,
        "d_c_rel_spread": float(np.std(d_c[has]) / d_c_med),
        "alpha_m_per_unit": alpha,
        "planes_fitted": int(has.sum()),
        "plane_inlier_ratio_median": float(np.median(plane_inl)),
        "up_in_model": up.tolist(),
        "pose_outliers": int(bad.sum()),
    }

    # ---- placement
    align: dict[str, Any] = {"kind": "none"}
    gps_enu = None
    if gps is not None:
        times = np.array([f.timestamp_s for f in reg])
        gps_enu = _gps_at_frames(gps, times, cfg.max_gps_gap_s)
        ok = np.isfinite(gps_enu).all(axis=1) & good
        if ok.sum() < 2:
            if claimed:  # a secondary model that the GPS cannot place is not used
                raise ModelRejected(f"only {int(ok.sum())} of its frames have GPS; cannot align")
            log.warning("GPS overlaps fewer than 2 registered frames; using a local frame")
            gps_enu = None
    if gps_enu is not None:
        ok = np.isfinite(gps_enu).all(axis=1) & good
        sim = cfg.gps_fit == "similarity"
        fit, inl2 = robust_fit_2d(c_lv[ok, :2], gps_enu[ok, :2], sim, cfg.gps_outlier_k)
        s_sim = robust_fit_2d(c_lv[ok, :2], gps_enu[ok, :2], True, cfg.gps_outlier_k)[0].scale
        if sim:  # the GPS scale replaces α
            c_lv, p_lv = c_lv * fit.scale, p_lv * fit.scale
            scale["alpha_m_per_unit"] = alpha * fit.scale
        R3 = rotation_from_euler_xyz(0.0, 0.0, fit.yaw_rad)  # = fit.R about the vertical
        c_h = c_lv @ R3.T + np.array([*fit.t, 0.0])  # horizontally placed, not yet vertically
        p_h = p_lv @ R3.T + np.array([*fit.t, 0.0])
        tilt = _fit_vertical_tilt(c_h, gps_enu, ok & np.isfinite(gps_enu[:, 2]), cfg)
        if tilt is not None:
            R_t, pivot, tilt_deg = tilt
            c_h = (c_h - pivot) @ R_t.T + pivot
            p_h = (p_h - pivot) @ R_t.T + pivot
            R3 = R_t @ R3
        dz = float(np.median(gps_enu[ok, 2] - c_h[ok, 2]))
        c_w = c_h + [0.0, 0.0, dz]
        p_w = p_h + [0.0, 0.0, dz]
        z_res = gps_enu[ok, 2] - c_w[ok, 2]
        resid = np.linalg.norm(c_w[ok, :2] - gps_enu[ok, :2], axis=1)
        spread = float(np.ptp(gps_enu[ok, :2], axis=0).max())
        align = {
            "kind": f"2d_{cfg.gps_fit}",
            "n_frames_with_gps": int(ok.sum()),
            "n_inliers": int(inl2.sum()),
            "rms_m": float(np.sqrt(np.mean(resid[inl2] ** 2))),
            "max_m": float(resid.max()),
            "rotation_deg": math.degrees(fit.yaw_rad),
            "gps_scale_over_height_scale": float(s_sim) if not sim else 1.0,
            "gps_extent_m": spread,
            "vertical_offset_m": dz,
            "vertical_tilt_deg": tilt[2] if tilt is not None else 0.0,
            "vertical_rms_m": float(np.sqrt(np.mean(z_res**2))),
        }
        if spread < 2.0:
            log.warning("model %d: GPS positions span only %.1f m: weak 2D alignment", k, spread)
        # A pose far off a good GPS fit is a bad registration (e.g. the planar two-fold
        # ambiguity), not GPS noise: drop it like the heading/distance outliers above.
        rms_in = align["rms_m"]
        far = ~inl2 & (resid > max(3.0 * rms_in, cfg.gps_pose_outlier_min_m))
        for j, r_j in zip(np.flatnonzero(ok)[far], resid[far], strict=True):
            good[j] = False
            outliers[reg[j].filename] = (
                f"registered by COLMAP (sparse/{k}) but {r_j:.2f} m off the GPS fit of its "
                f"model (rms {rms_in:.3f} m); dropped as a bad pose"
            )
        align["pose_outliers_dropped"] = int(far.sum())
    else:
        # Local frame: first camera at the origin, its forward (-y camera axis) along +y.
        fwd = -R_wc_lv[0][:, 1]
        R3 = rotation_from_euler_xyz(0.0, 0.0, math.atan2(fwd[0], fwd[1]))  # forward onto north
        c_w, p_w = c_lv @ R3.T, p_lv @ R3.T
    R_wc = np.einsum("ij,njk->nik", R3, R_wc_lv)

    # ---- what this model contributes: consistent frames no larger model already gave, and
    # the points those frames observe
    use = np.array([good[i] and f.filename not in claimed for i, f in enumerate(reg)])
    if not use.any():
        raise ModelRejected("all its consistent frames are already in a larger model")
    use_ids = {
        im_id
        for im_id, nm in img_id_name.items()
        if nm in {reg[i].filename for i in np.flatnonzero(use)}
    }
    keep = np.array(
        [any(el.image_id in use_ids for el in rec.points3D[int(p)].track.elements) for p in pids],
        dtype=bool,
    )
    return ModelGeo(
        index=k,
        frames=[reg[i] for i in np.flatnonzero(use)],
        R_wc=R_wc[use],
        c_w=c_w[use],
        p_w=p_w[keep],
        rgb=rgb[keep],
        scale=scale,
        align=align,
        outliers=outliers,
    )
