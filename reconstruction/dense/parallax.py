"""Dense height of one pair above its road plane: plane + parallax matching.

1. Both images are resampled onto image a's ideal (undistorted) pixel grid, image b through the
   pair's road homography (I_w(x) = I_b(H x)): the road is in place, and a point at height η
   above it is displaced along the line through the epipole by the parallax s(η)
   (``geometry.PlaneParallax``).
2. Init: a ZNCC sweep over heights on a coarser grid (``matching.sweep``) or OpenCV's DIS
   optical flow projected on the epipolar direction (``DenseHeightConfig.init``).
3. 1D Lucas-Kanade refinement of s with a local gain and offset, and its variance from the
   window's residual and texture (``matching.refine``).
4. The same from b to a; pixels whose two parallaxes disagree (occlusions, mismatches) are
   invalid, as are textureless, saturated or dark windows, low ZNCC, pixels next to the epipole
   and pixels whose own sample lies outside image b or whose window keeps fewer than
   ``checks.min_window_samples`` samples inside both images: a window that crosses the edge of
   the overlap is matched on its part inside (``matching``), and image b is resampled beyond
   image a's grid by the matches' reach (``warp``).
   Accepted pixels next to an occlusion or a step take the match of a window beside them on
   their own side (``shifted``, ``DenseHeightConfig.shifted_windows``); those whose parallax
   gradient (a plane fitted to the pass's parallaxes around them) is significant are matched
   again in windows slanted by it (a steep defect wall; ``slanted``,
   ``DenseHeightConfig.slant_sigmas``); pixels whose window's parallaxes no plane describes (a
   step) are refused (``DenseHeightConfig.step_plane_px``).
5. s -> η by the exact plane + parallax relation; var(η) = (dη/ds)² var(s) + (η σ_scale)².
6. Pixels left invalid (but not by the left-right or step tests) are matched again, steps 1-5,
   on a grid coarser by 2 (started from the first sweep's heights) and take its heights where
   it passes, with its variance widened by
   the relief in its window (``pyramid``, ``DenseHeightConfig.fallback_levels``); then the
   optional bilateral mean. Which check refused a pixel: ``DenseHeight.reject`` (``checks``).

Pure function of the images, the camera and the pair's R, t and plane (``dense_height``).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from roadsurf.core.camera import Camera
from roadsurf.core.errors import RoadsurfError
from roadsurf.reconstruction.dense.checks import (
    REJECT_GEOMETRY,
    REJECT_LR,
    REJECT_OUTSIDE,
    REJECT_UNMATCHED,
    checks,
)
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.geometry import PlaneParallax
from roadsurf.reconstruction.dense.matching import (
    INSIDE_MIN,
    fill_unswept,
    gaussian,
    refine,
    sample,
    sweep,
)
from roadsurf.reconstruction.dense.pyramid import LevelMatch, fill_from_coarse, prior_on_grid
from roadsurf.reconstruction.dense.runtime import cpu_threads, heap_blocks, torch_device
from roadsurf.reconstruction.dense.shifted import shifted_refine
from roadsurf.reconstruction.dense.slanted import plane_fit, slanted_refine
from roadsurf.reconstruction.dense.warp import overlap_crop, reach_px, resample_pair

log = logging.getLogger(__name__)

# a pair is matched again deeper (DenseHeightConfig.max_depth_limit_m) when more than
# DEEP_MIN_SHARE of its pixels hold the core of a patch (DEEP_CORE_PX wide) whose sweep starts
# at DEEP_SHARE of the search depth or deeper: a floor, not the overlap's edge band or stray
# matches. 36-frame drives: ordinary pairs 0-14 core pixels of ~180,000 (edge band and
# strays: 1,700-2,500 before the erosion), pairs over a 260-290 mm pothole 1,332 and 2,587
DEEP_SHARE = 0.9
DEEP_MIN_SHARE = 0.002
DEEP_CORE_PX = 9
DEEP_EDGE_PX = 31  # ... and the patch's core at least half this inside the matched part (px)


@dataclass
class DenseHeight:
    """Per-pixel height of image a's work grid (``scale`` x the image) above the pair's road."""

    height_m: np.ndarray  # (h, w) float32 height above the road plane (m), NaN where invalid
    var_m2: np.ndarray  # (h, w) float32 its variance (m²), NaN where invalid
    valid: np.ndarray  # (h, w) bool
    shift_px: np.ndarray  # (h, w) float32 parallax along the epipolar direction (px, work grid)
    ncc: np.ndarray  # (h, w) float32 ZNCC of the matched windows (−)
    model: PlaneParallax  # the plane + parallax model of the work grid (its K)
    scale: float  # work grid = image x scale
    timings_s: dict[str, float] = field(default_factory=dict)
    # (h, w) int8: the grid a valid pixel's height was matched on (0 = the work grid, k = the
    # fallback grid coarser by 2^k, ``dense.pyramid``), -1 where invalid; None: all level 0
    level: np.ndarray | None = None
    # (h, w) uint8 the checks that refused each pixel on the work grid (``dense.checks``
    # REJECT_* bits, 0 = passed; a pixel filled from a coarser grid keeps its flags)
    reject: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.height_m.shape  # type: ignore[return-value]

    def work_px(self) -> tuple[np.ndarray, np.ndarray]:
        """(h, w) u, v pixel coordinates of the work grid (ideal px of ``model.K``)."""
        h, w = self.shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        return u, v

    def ideal_px(self) -> tuple[np.ndarray, np.ndarray]:
        """(h, w) u, v ideal pixel coordinates of the work grid in the full-size image a."""
        u, v = self.work_px()
        return (u + 0.5) / self.scale - 0.5, (v + 0.5) / self.scale - 0.5

    def points_cam_a(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) camera-a points (m) of the valid pixels, and their (N,) height variance."""
        u, v = self.work_px()
        m = self.valid
        X = self.model.points_cam_a(self.height_m[m].astype(float), u[m], v[m])
        return X, self.var_m2[m].astype(float)


def dense_height(
    img_a: np.ndarray,
    img_b: np.ndarray,
    camera: Camera,
    R_b_from_a: np.ndarray,
    t_b_from_a_m: np.ndarray,
    plane: np.ndarray,
    H: np.ndarray | None = None,
    cfg: DenseHeightConfig | None = None,
    device: str | torch.device | None = None,
    frame_dt_s: float | None = None,
) -> DenseHeight:
    """Dense height of image a's pixels above the pair's road plane (module docstring).

    img_a, img_b: (height, width) uint8 grey images (raw, as recorded); R, t: X_b = R X_a + t
    (m); plane: (p0, p1, p2) with z = p0 x + p1 y + p2 in camera a (m). ``H`` (the pair's
    estimated road homography, ideal px) is only compared with the one R, t and the plane give,
    which is the one used (the parallax relation holds for it exactly). With a rolling shutter
    (``camera.readout_s`` > 0) and ``frame_dt_s`` (b's timestamp minus a's, s; negative when
    image a is the later frame) each image is resampled from the rows that saw the road
    (``dense.rolling``). Pixels that fail on the work
    grid are matched again on coarser grids (``DenseHeightConfig.fallback_levels``,
    ``dense.pyramid``)."""
    cfg = cfg or DenseHeightConfig()
    t0 = time.perf_counter()
    for name, img in (("img_a", img_a), ("img_b", img_b)):
        if img.ndim != 2 or img.shape != (camera.height, camera.width) or img.dtype != np.uint8:
            raise RoadsurfError(
                f"{name}: expected a ({camera.height}, {camera.width}) uint8 grey image "
                f"(the camera's size), got {img.shape} {img.dtype}"
            )
    pp = PlaneParallax.from_pair(R_b_from_a, t_b_from_a_m, plane, camera.K)
    if H is not None and np.all(np.isfinite(H)):
        _compare_homography(pp.H, np.asarray(H, float), camera)
    dev = device if isinstance(device, torch.device) else torch_device(device or cfg.device)
    s = cfg.work_scale(camera.width, camera.height)
    ppw = pp.scaled(s) if s != 1.0 else pp
    rs = None
    if camera.readout_s > 0 and frame_dt_s is not None and frame_dt_s != 0:
        rs = (np.asarray(R_b_from_a, float), np.asarray(t_b_from_a_m, float), plane, frame_dt_s)
    timings: dict[str, float] = {}
    with torch.no_grad(), cpu_threads(dev, cfg.cpu_threads), heap_blocks(dev):
        lv = _match_level(img_a, img_b, camera, pp, s, rs, cfg, dev, timings)
        deeper = cfg.deepest_search_m(camera.height_m)
        n_deep, n_seen = _deep_pixels(lv, cfg.max_depth_m)
        if deeper > cfg.max_depth_m and n_deep > DEEP_MIN_SHARE * max(n_seen, 1):
            log.info(
                "dense: %d of %d px start at %.0f mm or deeper (search %.0f mm): matched "
                "again down to %.0f mm", n_deep, n_seen,
                1000 * DEEP_SHARE * cfg.max_depth_m, 1000 * cfg.max_depth_m, 1000 * deeper,
            )  # fmt: skip
            # once, straight to the deepest search (the test is tuned at the first depth)
            again = dataclasses.replace(cfg, max_depth_m=deeper, max_depth_limit_m=deeper)
            return dense_height(
                img_a, img_b, camera, R_b_from_a, t_b_from_a_m, plane, H, again, dev, frame_dt_s
            )
        level = np.where(lv.valid, 0, -1).astype(np.int8)
        for k in range(1, cfg.fallback_levels + 1):
            sk = s * 0.5**k
            if lv.valid.all() or min(camera.width, camera.height) * sk < cfg.sweep_min_px:
                break
            t1 = time.perf_counter()
            coarse = _match_level(img_a, img_b, camera, pp, sk, rs, cfg, dev, {}, lv)
            filled = fill_from_coarse(lv, coarse, ppw, sk / s, int(cfg.window_px) | 1)
            level[filled] = k
            timings[f"fallback{k}"] = time.perf_counter() - t1
    eta, valid = lv.height_m.astype(np.float64), lv.valid
    if cfg.smooth_px > 0:
        eta = _smooth(np.nan_to_num(eta), valid, cfg.smooth_px, cfg.smooth_range_m)
    timings["total"] = time.perf_counter() - t0
    return DenseHeight(
        np.where(valid, eta, np.nan).astype(np.float32), lv.var_m2, valid, lv.shift_px, lv.ncc,
        ppw, s, {k: round(v, 4) for k, v in timings.items()}, level, lv.reject,
    )  # fmt: skip


def _deep_pixels(lv: LevelMatch, max_depth_m: float) -> tuple[int, int]:
    """(core pixels of the patches whose match starts at DEEP_SHARE of the search depth or
    deeper, pixels with a start inside both images): the sweep's best height sits at the bottom
    of its range where the floor lies beyond it (such pixels then fail the checks: a 200 mm
    pothole searched to 120 mm kept 5 of its 1,528 floor pixels); the final heights when there
    was no sweep (the DIS init)."""
    e = lv.init_eta_fwd if lv.init_eta_fwd is not None else lv.height_m
    fin = np.isfinite(e) & ((lv.reject & (REJECT_OUTSIDE | REJECT_UNMATCHED)) == 0)
    with np.errstate(invalid="ignore"):
        deep = (fin & (e <= -DEEP_SHARE * max_depth_m)).astype(np.uint8)
    core = cv2.erode(deep, np.ones((DEEP_CORE_PX, DEEP_CORE_PX), np.uint8))
    # away from the overlap's edge, whose band of bottom starts widens with the search depth
    inner = cv2.erode(fin.astype(np.uint8), np.ones((DEEP_EDGE_PX, DEEP_EDGE_PX), np.uint8))
    return int((core & inner).sum()), int(fin.sum())


def _match_level(
    img_a: np.ndarray,
    img_b: np.ndarray,
    camera: Camera,
    pp: PlaneParallax,
    s: float,
    rs: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None,
    cfg: DenseHeightConfig,
    dev: torch.device,
    timings: dict[str, float],
    prior: LevelMatch | None = None,
) -> LevelMatch:
    """Steps 1-5 of the module docstring on the grid of image a resized by ``s``: unsmoothed
    heights, their variance and validity on that grid (NaN / False where invalid). ``prior``: a
    finer grid's match of the same pair (image a resized by ``s_prior``) whose sweep heights
    start this one instead of a sweep of its own (a height is the same on every grid; the sweep
    runs on a grid of about ``sweep_min_px`` px whatever the level, so a second sweep would
    only repeat the first)."""
    t0 = time.perf_counter()
    ppw = pp.scaled(s) if s != 1.0 else pp
    hf, wf = int(round(camera.height * s)), int(round(camera.width * s))
    out = LevelMatch.empty(hf, wf, s)
    # the grid is padded by the matches' reach: image b's samples of image a's edge pixels may
    # lie beyond image a's own grid (``dense.warp``); padded pixel (P, P) = work pixel (0, 0)
    P = reach_px(ppw, cfg, hf, wf)
    share: list[np.ndarray] = []  # a rolling shutter's baseline share s_b - s_a per pixel
    A, B, mA, mB = resample_pair(img_a, img_b, camera, pp.H, s, rs, P, share)
    timings["resample"] = time.perf_counter() - t0
    crop = overlap_crop(mA & mB, P, cfg)
    if crop is None:  # image b sees none of image a's road
        return out
    r0, r1, c0, c1 = crop
    # only the part of image a that image b sees (with the parallax's reach) is matched: its
    # own sub-grid and model (u' = u - c0 + P, v' = v - r0 + P); the sub-grid's pixels within
    # image a's grid are written back (sl of the output, sub of the sub-grid)
    A, B, mA, mB = (x[r0:r1, c0:c1] for x in (A, B, mA, mB))
    f_rs = share[0][r0:r1, c0:c1] if share else None
    r0, r1, c0, c1 = r0 - P, r1 - P, c0 - P, c1 - P
    ppc = ppw.cropped(c0, r0) if (r0, c0) != (0, 0) else ppw
    o0, o1, q0, q1 = max(r0, 0), min(r1, hf), max(c0, 0), min(c1, wf)
    sl, sub = np.s_[o0:o1, q0:q1], np.s_[o0 - r0 : o1 - r0, q0 - c0 : q1 - c0]
    ss = min(1.0, max(float(cfg.sweep_scale), cfg.sweep_min_px / min(hf, wf)))
    h, w = A.shape
    v_np, u_np = np.mgrid[0:h, 0:w].astype(np.float64)
    wx_np, wy_np, nw_np = ppc.direction(u_np, v_np)
    nr_np = ppc.n_dot_ray(u_np, v_np)

    def t_(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float32, device=dev)[None, None]

    At, Bt = gaussian(t_(A), cfg.blur_px), gaussian(t_(B), cfg.blur_px)
    mAt, mBt = t_(mA.astype(np.float32)), t_(mB.astype(np.float32))
    wx, wy, nw, nr = t_(wx_np), t_(wy_np), t_(nw_np), t_(nr_np)
    t1 = time.perf_counter()
    pf = pr = None
    if prior is not None and prior.init_eta_fwd is not None:
        ratio = s / prior.scale
        pf = t_(prior_on_grid(prior.init_eta_fwd, ratio, r0, c0, h, w))
        if prior.init_eta_rev is not None:
            pr = t_(prior_on_grid(prior.init_eta_rev, ratio, r0, c0, h, w))
    s_fwd, e_fwd = _init(cfg, At, Bt, mBt, mAt, ppc, wx, wy, nw, nr, ss, False, pf)
    s_rev, e_rev = (
        _init(cfg, Bt, At, mAt, mBt, ppc, wx, wy, nw, nr, ss, True, pr)
        if cfg.lr_check
        else (None, None)
    )
    t2 = time.perf_counter()
    win = int(cfg.window_px) | 1
    fwd = refine(At, Bt, mBt, wx, wy, s_fwd, win, cfg.refine_iters, cfg.noise_dn, mAt)
    flags = checks(cfg, fwd, mAt, mBt, t_(A), t_(B), wx, wy, win)
    if s_rev is not None:
        it_rev = cfg.refine_iters if cfg.lr_refine_iters < 0 else cfg.lr_refine_iters
        rev = refine(Bt, At, mAt, wx, wy, s_rev, win, it_rev, cfg.noise_dn, mBt)
        ys, xs = torch.meshgrid(
            torch.arange(h, device=dev, dtype=torch.float32),
            torch.arange(w, device=dev, dtype=torch.float32),
            indexing="ij",
        )
        x2 = xs[None, None] + fwd.shift * wx
        y2 = ys[None, None] + fwd.shift * wy
        back = sample(rev.shift, x2, y2)
        flags |= ((fwd.shift + back).abs() > cfg.lr_max_px).to(torch.uint8) * REJECT_LR
    if cfg.shifted_windows and cfg.refine_iters > 0 and prior is None:  # steps: windows aside
        fwd, _ = shifted_refine(At, Bt, mBt, mAt, wx, wy, fwd, flags, win, cfg)
    t3 = time.perf_counter()
    if cfg.slant_sigmas > 0 and cfg.refine_iters > 0:  # walls: windows slanted by ∇s
        fwd, _ = slanted_refine(At, Bt, mBt, mAt, wx, wy, fwd, flags == 0, win, cfg)
    if cfg.step_plane_px > 0:  # steps: a window no plane of parallax describes
        rms = plane_fit(fwd.shift, flags == 0, win)[3]
        flags |= (rms >= cfg.step_plane_px).to(torch.uint8) * REJECT_GEOMETRY
    t4 = time.perf_counter()
    shift = fwd.shift[0, 0].double().cpu().numpy()
    var_s = fwd.var[0, 0].double().cpu().numpy()
    if cfg.refine_iters > 0:  # what the iteration has left: about its last step
        var_s = var_s + fwd.last_step[0, 0].double().cpu().numpy() ** 2
    ncc = fwd.ncc[0, 0].cpu().numpy()
    reject = flags[0, 0].cpu().numpy()
    # a rolling shutter's resampled pair shows the parallax of s_b - s_a of the motion
    # (dense.rolling): divided by it, as the pair's own baseline would show it
    f = 1.0 if f_rs is None else f_rs
    eta = ppc.height_from_shift(shift / f, u_np, v_np, nw_np)
    deta = ppc.dheight_dshift(shift / f, u_np, v_np, nw_np) / f
    var = deta * deta * var_s + (cfg.scale_rel_sigma * eta) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        near = nw_np / max(abs(float(ppc.E[2])), 1e-12) < cfg.min_epipole_px * s
    with np.errstate(invalid="ignore"):
        far = ~((eta >= -cfg.max_depth_m - 0.01) & (eta <= cfg.max_height_m + 0.01))
    bad = ~(np.isfinite(eta) & np.isfinite(var)) | near | far
    reject |= np.where(bad, REJECT_GEOMETRY, 0).astype(np.uint8)
    valid = reject == 0
    out.height_m[sl] = np.where(valid, eta, np.nan)[sub]
    out.var_m2[sl] = np.where(valid, var, np.nan)[sub]
    out.valid[sl] = valid[sub]
    out.shift_px[sl] = shift[sub]
    out.ncc[sl] = ncc[sub]
    out.reject[sl] = reject[sub]
    for e, name in ((e_fwd, "init_eta_fwd"), (e_rev, "init_eta_rev")):
        if e is not None:
            full = np.full((hf, wf), np.nan, np.float32)
            full[sl] = e[0, 0].cpu().numpy()[sub]
            setattr(out, name, full)
    timings.update(init=t2 - t1, refine=t3 - t2, slant=t4 - t3)
    return out


# --------------------------------------------------------------------------- steps


def _compare_homography(Hp: np.ndarray, He: np.ndarray, camera: Camera) -> None:
    """Log how far the pair's estimated homography is from the one its R, t and plane give."""
    w, h = camera.width, camera.height
    c = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1.0]])
    p, q = c @ Hp.T, c @ He.T
    d = np.linalg.norm(p[:, :2] / p[:, 2:] - q[:, :2] / q[:, 2:], axis=1).max()
    log.debug("dense: estimated vs plane homography differ by %.2f px at the corners", d)


def _smooth(eta: np.ndarray, valid: np.ndarray, sigma_px: float, range_m: float) -> np.ndarray:
    """Bilateral mean of the valid heights (invalid pixels, set 1 m away, get no weight). Only
    the rows holding valid pixels, padded by the kernel's radius, are filtered (the overlap is
    about 60 % of an image). Whole rows, as OpenCV's vector loop and its scalar tail differ
    in the last bit. OpenCV scales its float range table by the filtered array's min and max:
    the band holds every valid pixel (the minimum) and, when the image has an invalid pixel
    (the 1 m maximum), one of them too (a row beside the band, or in it). So the result is the
    whole image's, bit for bit."""
    f = np.where(valid, eta, 1.0).astype(np.float32)
    d = 2 * int(np.ceil(2 * sigma_px)) + 1
    rows = np.flatnonzero(valid.any(1))
    out = np.full(f.shape, np.nan)
    if not len(rows):
        return out
    r0, r1 = max(rows[0] - d // 2, 0), min(rows[-1] + d // 2 + 1, f.shape[0])
    out[r0:r1] = cv2.bilateralFilter(f[r0:r1], d, range_m, sigma_px)
    return np.where(valid, out, np.nan)


def _init(
    cfg: DenseHeightConfig,
    ref: torch.Tensor,
    tgt: torch.Tensor,
    tgt_mask: torch.Tensor,
    ref_mask: torch.Tensor,
    pp: PlaneParallax,
    wx: torch.Tensor,
    wy: torch.Tensor,
    nw: torch.Tensor,
    nr: torch.Tensor,
    ss: float,
    reverse: bool,
    prior_eta: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Starting parallax (1, 1, h, w) px of ref's pixels in tgt along ŵ (its negative for the
    reverse direction b -> a), and the swept height it comes from (m; None for DIS). With
    ``prior_eta`` (a height field on this grid, m) that height is used instead of a sweep."""
    sign = -1.0 if reverse else 1.0
    hb, ha = pp.h_b, pp.h_a

    def shift_on_grid(eta: torch.Tensor) -> torch.Tensor:
        k = eta * nr / (hb * (ha - eta))
        return sign * k * nw / (1.0 - k * float(pp.E[2]))

    if prior_eta is not None and cfg.init == "sweep":
        return shift_on_grid(prior_eta), prior_eta
    if cfg.init == "dis":
        if ref.device.type != "cpu":
            log.debug("dense: DIS runs on the CPU")
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        a8 = np.clip(ref[0, 0].cpu().numpy() + 0.5, 0, 255).astype(np.uint8)
        b8 = np.clip(tgt[0, 0].cpu().numpy() + 0.5, 0, 255).astype(np.uint8)
        flow = dis.calc(a8, b8, None)
        ft = torch.as_tensor(flow, device=ref.device).permute(2, 0, 1)[None]
        return ft[:, :1] * wx + ft[:, 1:2] * wy, None
    h, w = ref.shape[-2:]

    def down(x: torch.Tensor) -> torch.Tensor:
        if ss == 1.0:
            return x
        return F.interpolate(
            x, scale_factor=ss, mode="bilinear", antialias=True, recompute_scale_factor=False
        )

    r_s, t_s = down(ref), down(tgt)
    # the masks' coarse samples: 1 only where all the fine pixels they average are image data
    rm_s, tm_s = down(ref_mask), down(tgt_mask)
    hs, ws = r_s.shape[-2:]
    # the sweep grid's pixel u'' = ss (u' + 0.5) - 0.5 of the work grid's u'
    pps = pp.scaled(ss)
    v_np, u_np = np.mgrid[0:hs, 0:ws].astype(np.float64)
    wxs_np, wys_np, nws_np = pps.direction(u_np, v_np)
    nrs_np = pps.n_dot_ray(u_np, v_np)

    def t_(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(x, dtype=torch.float32, device=ref.device)[None, None]

    wxs, wys, nws, nrs = t_(wxs_np), t_(wys_np), t_(nws_np), t_(nrs_np)
    lo, hi = -float(cfg.max_depth_m), float(cfg.max_height_m)
    span = np.abs(pps.shift_from_height(hi, u_np, v_np) - pps.shift_from_height(lo, u_np, v_np))
    n = int(np.ceil(np.nanmax(span) / cfg.sweep_step_px)) + 1 if np.isfinite(span).any() else 2
    values = torch.linspace(lo, hi, max(n, 3), device=ref.device, dtype=torch.float32)
    e2 = float(pps.E[2])

    def shift_of(eta: torch.Tensor) -> torch.Tensor:
        k = eta * nrs / (hb * (ha - eta))
        return sign * k * nws / (1.0 - k * e2)

    win = int(cfg.window_px) | 1
    res = sweep(r_s, t_s, wxs, wys, values, shift_of, win, tm_s, rm_s)
    # the band next to the overlap's edge that no candidate saw with enough samples starts
    # from its swept neighbours (a window's reach, win pixels of the sweep grid), and so do the
    # sweep pixels outside the overlap (part of them beyond either image at zero parallax): they
    # have no match, the sweep takes the candidate that pulls their window into the target, and
    # the upsampling below would carry that up to a sweep pixel into the overlap
    inside = (tm_s >= INSIDE_MIN) & (rm_s >= INSIDE_MIN)
    eta_s = fill_unswept(res.value, torch.where(inside, res.ncc, -2.0), win)
    if ss != 1.0:  # back on the work grid (sweep coordinates of work pixels, clamped)
        ys, xs = torch.meshgrid(
            torch.arange(h, device=ref.device, dtype=torch.float32),
            torch.arange(w, device=ref.device, dtype=torch.float32),
            indexing="ij",
        )
        xs = (ss * (xs + 0.5) - 0.5).clamp(0, ws - 1)[None, None]
        ys = (ss * (ys + 0.5) - 0.5).clamp(0, hs - 1)[None, None]
        eta_s = sample(eta_s, xs, ys)
    return shift_on_grid(eta_s), eta_s
