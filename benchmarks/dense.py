"""Dense two-view height (issue 29): accuracy and speed on rendered pairs, and the matcher
comparison.

A pair of consecutive frames is rendered by the simulator (a pothole in the overlap), with its
true poses; the dense height of every pixel of image a (``reconstruction.dense``) is compared
with the true height of the surface point the pixel sees (ray cast on the world's height field),
with the true geometry (matching error only) and with the pair's own reconstruction (the
pipeline's case), next to the sparse points of that reconstruction. ``synthetic_pair`` renders
an analytic pair (flat textured road, bowl pothole, optional crack, any mount pitch) for tests.

    python -m benchmarks.dense                     # 320x240, both inits, CPU
    python -m benchmarks.dense --size 640x480 --device cuda --repeat 5
    python -m benchmarks.dense --speed --device cuda --json OUT.json   # pairs/s, CPU agreement

Figures: MAE of the height on flat road and inside the pothole (with the estimated geometry:
after removing a plane fitted to the flat-road differences, i.e. what a local road fit sees),
the same against the truth averaged over the matching window (``*_win``: what a window match
can resolve), the parallax precision (px, flat-road MAD of the parallax error), coverage, the
median |error| / σ (0.67 when the variance is right) and seconds per pair (1 CPU thread).

Measured (potholes scenario, seed 202, 2 shared CPU cores, busy machine):

    size     init   flat  pothole  flat_win  shift MAD (win)  pothole cov.  s/pair
    320x240  sweep  1.13  2.14     0.62      0.148 (0.075)    0.89          0.19-0.32
    320x240  DIS    1.13  2.17     0.62      0.148 (0.075)    0.86          0.16-0.24
    640x480  sweep  0.64  1.30     0.39      0.162 (0.096)    0.94          0.37-0.71
    640x480  DIS    0.64  1.31     0.39      0.162 (0.096)    0.95          0.8
    sparse points of the same pair: 320x240 1.27 / 2.79 mm (237 points, 59 in the pothole),
    640x480 0.72 / 1.51 mm (774 points, 70 in the pothole)

Both inits converge to the same heights after the 1D Lucas-Kanade refinement; the sweep is
kept as the default: it is torch (CPU and CUDA from the same code), searches the whole height
range globally, and covered more of the pothole at 320x240. Window 5 px without pre-blur was
best at 640x480 (window 7: pothole 1.71 mm; blur 0.7 px: flat 0.85 mm). On the analytic pair
(white noise only) the parallax precision is 0.076 px (320x240) and 0.04 px (640x480).

Whole drives (``roadsurf simulate --scenario S --frames 20``, ``roadsurf run`` with
``mapping: {surface_source: dense}``, ``roadsurf evaluate``; aligned MAE, mm):

    scenario    surface  flat  in-defect  recall  depth MAE  globalmap s  detection s
    potholes    sparse   1.63  2.45       100 %   2.33       1.9          2.8
    potholes    dense    1.00  1.06       100 %   2.68       31           43
    potholes    dense/2  1.09  1.23       100 %   2.43       14           11
    vibration   sparse   2.45  6.61        75 %   2.40       3.0          9.7
    vibration   dense    1.39  3.08       100 %   1.94       39           31

(dense/2: ``dense: {scale: 0.5}``, 3.7 mm raster. The dense surface and mosaic are on the
images' 1.8 mm ground sampling, so detection reads 7.7x more cells.)

After the speed work (session 21; full 60/80-frame drives, ``roadsurf simulate --scenario S``,
``roadsurf run D --out R [--config dense.yaml]`` with ``mapping: {surface_source: dense}``,
``roadsurf evaluate R --truth D/truth``; aligned MAE, mm; 2 shared CPU cores, load ~11):

    scenario      surface  flat  in-defect  2-view cov.  frame acc.  P / R        depth MAE
    potholes      sparse   1.63  3.24       99.2 %       88.3 %      100 / 100 %  2.00
    potholes      dense    1.07  1.46       99.2 %       100 %       100 / 100 %  2.13
    tilted (25°)  sparse   1.47  2.90       93.6 %       93.3 %      100 / 87.5 % 3.01
    tilted (25°)  dense    1.17  2.05       98.2 %       98.3 %      100 / 87.5 % 3.21
    highway       sparse   1.37  2.56       99.2 %       100 %       100 / 83.3 % 2.41
    highway       dense    1.10  1.66       99.5 %       100 %       100 / 83.3 % 2.36
    tilted (45°)  sparse   1.77  3.36       28.6 %       93.3 %      85.7 / 75 %  5.74
    tilted (45°)  dense    1.37  2.28       95.3 %       100 %       100 / 75 %   5.43

(tilted 45°: ``roadsurf simulate --scenario tilted --mount-pitch 45``.)

potholes, whole run from scratch, same machine back to back: sparse 61.0 s wall / 42.6 CPU s,
dense 69.5 s / 60.8 CPU s (before: the dense globalmap + detection alone took 116 CPU s).
What changed: only the part of image a that b sees is matched, the b -> a check refines 2
steps, the raster cell is 2 matched pixels (3.7 mm; the heights are 5 px window means), the
pair heights get a 3 px bilateral mean (flat 1.19 -> 1.07, in-defect 1.58 -> 1.46 mm), malloc
serves the matcher's temporaries from its heap (the run's 256 KB mmap threshold cost 3.7x),
and detection's frame masks project cells through an affine grid -> ENU map. Matcher, 640 x
480 pair: 0.211 -> 0.125 CPU s (0.16 inside a run, with the heap trimmed after each pair).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.geometry import PlaneParallax
from roadsurf.reconstruction.dense.parallax import DenseHeight, dense_height


@dataclass
class RenderedPair:
    """Two rendered frames with the truth the dense height is checked against."""

    img_a: np.ndarray  # (h, w) uint8 grey
    img_b: np.ndarray
    camera: Camera
    R: np.ndarray  # true R_b_from_a
    t: np.ndarray  # true t_b_from_a (m)
    plane: np.ndarray  # true road plane in camera a (z = p0 x + p1 y + p2), fitted to the base
    eta_true: np.ndarray  # (h, w) true height above that plane of the point each pixel sees (m)
    depth_true: np.ndarray  # (h, w) defect depth at that point (m, >= 0)
    resid_true: np.ndarray  # (h, w) true residual (height - smooth road) there (m)


def render_pair(
    size: tuple[int, int] = (320, 240),
    scenario: str = "potholes",
    seed: int | None = None,
    min_depth_m: float = 0.02,
    **overrides: object,
) -> RenderedPair:
    """The first consecutive pair of ``scenario`` whose overlap holds a pothole at least
    ``min_depth_m`` deep (whole in image a), rendered at ``size`` (fx scaled with the width)."""
    from roadsurf.simulation.build import build_world
    from roadsurf.simulation.render import Renderer
    from roadsurf.simulation.scenarios import SCENARIOS, make_config
    from roadsurf.simulation.sensors import form_image

    w, h = size
    sc = SCENARIOS[scenario]
    kw = {"width": w, "height": h, "fx": 600.0 * w / 640.0, **overrides}
    cfg = make_config(scenario, **kw)  # type: ignore[arg-type]
    seed = sc.seed if seed is None else seed
    world = build_world(cfg, seed, sc.n_frames)
    cam = cfg.camera()
    ren = Renderer(world)
    poses = [world.pose(float(t)) for t in world.frame_times]
    best = None
    for k in range(len(poses) - 1):
        pa, pb = poses[k], poses[k + 1]
        for p in world.potholes:
            if p.depth_m < min_depth_m:
                continue
            c = np.array([p.shape.cx, p.shape.cy, 0.0])
            pad = 0.5 * p.shape.r_max  # the centre half of it in both frames
            ok = True
            for q in (pa, pb):
                for dx, dy in ((-pad, 0), (pad, 0), (0, -pad), (0, pad), (0, 0)):
                    X = q.R.T @ (c + [dx, dy, float(world.base(c[0], c[1]))] - q.C)
                    u, v = cam.project(X)
                    ok &= bool(8 <= u <= w - 9 and 8 <= v <= h - 9)
            if ok:
                best = k
                break
        if best is not None:
            break
    if best is None:
        raise RuntimeError(f"no pair of {scenario!r} (seed {seed}) sees a whole pothole")
    imgs = []
    for k in (best, best + 1):
        fr = ren.render(poses[k])
        rng = np.random.default_rng([seed, 1000 + k])
        gain = float(1.0 + cfg.exposure_var * rng.standard_normal())
        img = form_image(fr.radiance, cfg, cfg.speed_mps, gain, rng)
        imgs.append(img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
    pa, pb = poses[best], poses[best + 1]
    R = pb.R.T @ pa.R
    t = pb.R.T @ (pa.C - pb.C)
    eta, depth, resid, plane = _truth(world, cam, pa)
    return RenderedPair(imgs[0], imgs[1], cam, R, t, plane, eta, depth, resid)


def synthetic_pair(
    size: tuple[int, int] = (320, 240),
    pitch_deg: float = 0.0,
    baseline_m: float = 0.35,
    height_m: float = 1.1,
    pothole_depth_m: float = 0.04,
    pothole_radius_m: float = 0.12,
    crack_depth_m: float = 0.0,
    crack_width_m: float = 0.003,
    noise_dn: float = 2.0,
    seed: int = 0,
) -> RenderedPair:
    """Two views of a flat road (z = 0) with a bowl-shaped pothole (depth D (1 - (r/R)^4)) and
    optionally a straight crack (a V groove across the drive), textured with multi-scale noise,
    ray cast with 2x2 supersampling: a seeded pair with an exact height field. The camera
    (f = 600 px at 640 wide) looks down, tilted ``pitch_deg`` forward; b is ``baseline_m``
    ahead. The pothole and crack sit where both views see them."""
    from roadsurf.core.geometry import vehicle_from_cam_rotation, world_from_vehicle_rotation

    w, h = size
    f = 600.0 * w / 640.0
    cam = Camera(w, h, f, f, (w - 1) / 2, (h - 1) / 2, height_m, 15.0)
    Rwc = world_from_vehicle_rotation(0.0) @ vehicle_from_cam_rotation(pitch_deg, 0.0, 0.0)
    Ca = np.array([0.0, 0.0, height_m])
    Cb = Ca + np.array([0.0, baseline_m, 0.0])  # heading north: forward = +y
    # the ground point the image centre of a sees, moved half the baseline forward
    d0 = Rwc @ np.array([0.0, 0.0, 1.0])
    centre = Ca[:2] + (-height_m / d0[2]) * d0[:2] + [0.0, 0.5 * baseline_m]
    rng = np.random.default_rng(seed)
    g = 0.25 * height_m / f  # texture cells: a quarter of the nadir pixel footprint (m)
    # bounds: the image corners of both views on the road, plus the relief's reach
    uc = np.array([[-1, -1], [w, -1], [w, h], [-1, h]], float)
    dc = np.column_stack([(uc - [cam.cx, cam.cy]) / f, np.ones(4)]) @ Rwc.T
    foot = np.concatenate([C[:2] + (-C[2] / dc[:, 2:3]) * dc[:, :2] for C in (Ca, Cb)])
    lo, hi = foot.min(0) - 0.1, foot.max(0) + 0.1
    x0, y1 = lo[0], hi[1]
    nx, ny = int((hi[0] - lo[0]) / g) + 1, int((hi[1] - lo[1]) / g) + 1
    n = max(nx, ny)
    tex = np.zeros((n, n), np.float32)  # square (simple octaves), only ny x nx used
    for sig, amp in ((1.0, 1.0), (3.0, 1.0), (8.0, 0.8), (25.0, 0.6)):
        z = rng.standard_normal((n // int(sig) + 2, n // int(sig) + 2)).astype(np.float32)
        z = cv2.resize(z, (n, n), interpolation=cv2.INTER_CUBIC)
        tex += amp * cv2.GaussianBlur(z, (0, 0), max(sig * 0.6, 0.7))
    tex = (120.0 + 45.0 * tex / tex.std())[:ny, :nx].copy()
    X, Y = np.meshgrid(x0 + (np.arange(nx) + 0.5) * g, y1 - (np.arange(ny) + 0.5) * g)
    r = np.hypot(X - centre[0], Y - centre[1]) / pothole_radius_m
    zf = np.where(r < 1, -pothole_depth_m * (1 - r**4), 0.0)
    if crack_depth_m > 0:  # across the drive, 0.2 m behind the pothole's centre
        dist = np.abs(Y - (centre[1] - 0.2))
        zf = np.minimum(zf, np.where(dist < crack_width_m / 2, -crack_depth_m, 0.0))
    zf = zf.astype(np.float32)

    def at(field: np.ndarray, p: np.ndarray) -> np.ndarray:
        c = ((p[..., 0] - x0) / g - 0.5).astype(np.float32)
        rr = ((y1 - p[..., 1]) / g - 0.5).astype(np.float32)
        return cv2.remap(field, c, rr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def cast(C: np.ndarray, ss: int) -> tuple[np.ndarray, np.ndarray]:
        v, u = np.mgrid[0 : h * ss, 0 : w * ss].astype(np.float64)
        u, v = (u + 0.5) / ss - 0.5, (v + 0.5) / ss - 0.5
        d = np.stack([(u - cam.cx) / f, (v - cam.cy) / f, np.ones_like(u)], -1) @ Rwc.T
        t = -C[2] / d[..., 2]
        for _ in range(12):
            p = C[:2] + t[..., None] * d[..., :2]
            t = (at(zf, p).astype(float) - C[2]) / d[..., 2]
        p = C[:2] + t[..., None] * d[..., :2]
        return p, at(zf, p).astype(float)

    imgs = []
    for k, C in enumerate((Ca, Cb)):
        p, _ = cast(C, 2)
        img = cv2.resize(at(tex, p), (w, h), interpolation=cv2.INTER_AREA)
        img = img + noise_dn * np.random.default_rng([seed, k]).standard_normal(img.shape)
        imgs.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    p, z = cast(Ca, 1)
    R = Rwc.T @ Rwc  # no rotation between the views
    t = Rwc.T @ (Ca - Cb)
    # the road z = 0 in camera a: n_cam = Rwcᵀ (0, 0, -1) (away from the camera), d = height
    nc = Rwc.T @ np.array([0.0, 0.0, -1.0])
    plane = np.array([-nc[0] / nc[2], -nc[1] / nc[2], height_m / nc[2]])
    return RenderedPair(imgs[0], imgs[1], cam, R, t, plane, z, np.maximum(-z, 0.0), z)


def _truth(world, cam: Camera, pose) -> tuple[np.ndarray, ...]:
    """Per pixel of the frame at ``pose``: true height above the plane fitted to the smooth road
    under the footprint, defect depth and residual of the surface point the pixel sees."""
    w, h = cam.width, cam.height
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    n = cam.normalised_from_raw_px(np.column_stack([u.ravel(), v.ravel()]))
    d = np.column_stack([n, np.ones(len(n))]) @ pose.R.T  # world rays, camera z = 1
    C = pose.C
    z0 = float(world.base(np.array(C[0]), np.array(C[1])))
    t = (z0 - C[2]) / d[:, 2]
    xy = C[:2] + t[:, None] * d[:, :2]
    g = 0.0005
    x0, y1 = xy[:, 0].min() - 0.05, xy[:, 1].max() + 0.05
    cols = int((xy[:, 0].max() + 0.05 - x0) / g) + 1
    rows = int((y1 - xy[:, 1].min() + 0.05) / g) + 1
    f = world.evaluate(x0, y1, g, rows, cols, appearance=False)

    def at(field: np.ndarray, p: np.ndarray) -> np.ndarray:
        c = ((p[:, 0] - x0) / g - 0.5).astype(np.float32).reshape(-1, 256)
        r = ((y1 - p[:, 1]) / g - 0.5).astype(np.float32).reshape(-1, 256)
        return cv2.remap(field, c, r, cv2.INTER_LINEAR).ravel().astype(float)

    for _ in range(8):  # ray / height-field fixed point (nadir: converges fast)
        p = C[:2] + t[:, None] * d[:, :2]
        t = (at(f["height"], p) - C[2]) / d[:, 2]
    p = C[:2] + t[:, None] * d[:, :2]
    X = np.column_stack([p, C[2] + t * d[:, 2]])
    Xa = (X - C) @ pose.R  # camera a
    # plane fitted to the smooth road under the footprint (camera a)
    ii = np.linspace(0, len(p) - 1, 512).astype(int)
    B = np.column_stack([p[ii], at(f["base"], p[ii])])
    Ba = (B - C) @ pose.R
    A = np.column_stack([Ba[:, 0], Ba[:, 1], np.ones(len(Ba))])
    plane = np.linalg.lstsq(A, Ba[:, 2], rcond=None)[0]
    pp = PlaneParallax.from_pair(np.eye(3), np.array([0.0, 0.1, 0.0]), plane, np.eye(3))
    eta = (pp.h_a - Xa @ pp.n).reshape(h, w)
    depth = at(f["depth"], p).reshape(h, w)
    resid = (X[:, 2] - at(f["base"], p)).reshape(h, w)
    return eta, depth, resid, plane


def _detrend(err: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """err minus a plane (in pixel coordinates) fitted robustly to its flat-road part."""
    h, w = err.shape
    v, u = np.mgrid[0:h, 0:w].astype(float)
    m = flat & np.isfinite(err)
    if m.sum() < 10:
        return err
    A = np.column_stack([u[m], v[m], np.ones(m.sum())])
    coef = np.linalg.lstsq(A, err[m], rcond=None)[0]
    r = err[m] - A @ coef
    keep = np.abs(r) < 3 * 1.4826 * np.median(np.abs(r)) + 1e-9
    coef = np.linalg.lstsq(A[keep], err[m][keep], rcond=None)[0]
    return err - (coef[0] * u + coef[1] * v + coef[2])


def score(
    dh: DenseHeight, pair: RenderedPair, detrend: bool = False, cfg_window: int = 7
) -> dict[str, float]:
    """Height MAE on flat road and in the pothole (mm), parallax precision (px), coverage."""
    ua, va = dh.ideal_px()
    ui = np.clip(np.round(ua).astype(int), 0, pair.camera.width - 1)
    vi = np.clip(np.round(va).astype(int), 0, pair.camera.height - 1)
    eta_t = pair.eta_true[vi, ui]
    dep = pair.depth_true[vi, ui]
    flat = dep <= 0.0
    pot = dep > 0.005
    err = dh.height_m.astype(float) - eta_t
    if detrend:
        err = _detrend(err, flat & dh.valid)
    u, v = dh.work_px()
    serr = dh.shift_px - dh.model.shift_from_height(eta_t, u, v)
    m = dh.valid
    # the truth averaged over the matching window: what a window match can resolve
    win = int(cfg_window) | 1
    eta_s = cv2.blur(eta_t.astype(np.float32), (win, win)).astype(float)
    err_s = dh.height_m.astype(float) - eta_s
    if detrend:
        err_s = _detrend(err_s, flat & dh.valid)
    serr_s = dh.shift_px - dh.model.shift_from_height(eta_s, u, v)
    z = np.abs(err_s[m]) / np.sqrt(dh.var_m2[m])
    return {
        "flat_mae_mm": 1e3 * float(np.nanmean(np.abs(err[m & flat]))),
        "flat_p95_mm": 1e3 * float(np.nanpercentile(np.abs(err[m & flat]), 95)),
        "flat_mae_win_mm": 1e3 * float(np.nanmean(np.abs(err_s[m & flat]))),
        "pothole_mae_win_mm": 1e3 * float(np.nanmean(np.abs(err_s[m & pot]))),
        "pothole_mae_mm": 1e3 * float(np.nanmean(np.abs(err[m & pot])))
        if (m & pot).any()
        else np.nan,
        "shift_mad_px": float(1.4826 * np.nanmedian(np.abs(serr[m & flat]))),
        "shift_mad_win_px": float(1.4826 * np.nanmedian(np.abs(serr_s[m & flat]))),
        "shift_bias_px": float(np.nanmedian(serr[m & flat])),
        "coverage": float(m.mean()),
        "coverage_pothole": float(m[pot].mean()) if pot.any() else np.nan,
        # |error vs the window-averaged truth| / σ: 0.67 when the variance is right
        "z_median": float(np.median(z)),
    }


def sparse_score(pair: RenderedPair) -> tuple[dict[str, float], object]:
    """The pipeline's own reconstruction of the pair (SIFT, rotation_aware) and the error of its
    sparse points' heights (after the same flat-road plane removal)."""
    from roadsurf.reconstruction.api import reconstruct_features
    from roadsurf.reconstruction.config import ReconstructionConfig
    from roadsurf.reconstruction.features import detect

    rc = ReconstructionConfig()
    fa = detect(pair.img_a, rc.features)
    fb = detect(pair.img_b, rc.features)
    res = reconstruct_features(fa, fb, pair.camera, rc)
    if not res.ok:
        return {"status": res.status}, res  # type: ignore[dict-item]
    px = res.px_a
    ui = np.clip(np.round(px[:, 0]).astype(int), 0, pair.camera.width - 1)
    vi = np.clip(np.round(px[:, 1]).astype(int), 0, pair.camera.height - 1)
    # heights above the pair's plane; truth above the true plane: compare after a plane fit
    eta = np.asarray(res.plane_dist_m, float)
    err = eta - pair.eta_true[vi, ui]
    dep = pair.depth_true[vi, ui]
    flat = dep <= 0
    A = np.column_stack([px, np.ones(len(px))])
    coef = np.linalg.lstsq(A[flat], err[flat], rcond=None)[0]
    err = err - A @ coef
    pot = dep > 0.005
    return {
        "flat_mae_mm": 1e3 * float(np.mean(np.abs(err[flat]))),
        "pothole_mae_mm": 1e3 * float(np.mean(np.abs(err[pot]))) if pot.any() else np.nan,
        "n_points": float(len(px)),
        "n_in_pothole": float(pot.sum()),
    }, res


def speed(
    device: str, sizes: list[tuple[int, int]], repeat: int, pitches: list[float], cpu_check: bool
) -> dict[str, object]:
    """Pairs/s of ``dense_height`` on analytic pairs (``synthetic_pair``: 40 mm pothole, 2 DN
    noise) at each size and mount pitch, the per-step times, the heights' errors, and with
    ``cpu_check`` the largest height difference to the same pair matched on the CPU."""
    import torch

    from roadsurf.reconstruction.dense.parallax import torch_device

    dev = torch_device(device)
    out: dict[str, object] = {"device": str(dev), "torch": torch.__version__, "runs": []}
    if dev.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(dev)
    cfg = DenseHeightConfig(device=str(dev))
    runs: list[dict[str, object]] = []
    for w, h in sizes:
        for pitch in pitches:
            t0 = time.perf_counter()
            pair = synthetic_pair((w, h), pitch_deg=pitch, seed=1)
            t_render = time.perf_counter() - t0

            def one(c: DenseHeightConfig = cfg, p: RenderedPair = pair) -> DenseHeight:
                return dense_height(p.img_a, p.img_b, p.camera, p.R, p.t, p.plane, cfg=c)

            one()  # warm-up (CUDA context, kernels, allocator)
            times, steps = [], []
            for _ in range(repeat):
                t1 = time.perf_counter()
                dh = one()
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                times.append(time.perf_counter() - t1)
                steps.append(dh.timings_s)
            med = float(np.median(times))
            sc = score(dh, pair, cfg_window=cfg.window_px)
            rec: dict[str, object] = {
                "size": f"{w}x{h}",
                "pitch_deg": pitch,
                "s_per_pair_median": round(med, 4),
                "s_per_pair_min": round(float(np.min(times)), 4),
                "pairs_per_s": round(1.0 / med, 2),
                "steps_s": {k: float(np.median([st[k] for st in steps])) for k in steps[0]},
                "render_s": round(t_render, 2),
                **{k: round(float(v), 4) for k, v in sc.items()},
            }
            if cpu_check and dev.type != "cpu":
                ref = one(dataclasses.replace(cfg, device="cpu"))
                both = ref.valid & dh.valid
                rec["cpu_valid_agreement"] = round(float((ref.valid == dh.valid).mean()), 5)
                rec["cpu_max_height_diff_mm"] = round(
                    1e3 * float(np.abs(ref.height_m[both] - dh.height_m[both]).max()), 4
                )
            print(rec, flush=True)
            runs.append(rec)
    out["runs"] = runs
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--scenario", default="potholes")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--inits", default="sweep,dis")
    ap.add_argument("--set", action="append", default=[], help="DenseHeightConfig field=value")
    ap.add_argument(
        "--speed",
        action="store_true",
        help="pairs/s on analytic pairs (--sizes, --pitches) instead of the rendered comparison",
    )
    ap.add_argument("--sizes", default="640x480,1280x960")
    ap.add_argument("--pitches", default="0,30", help="mount pitches (deg) for --speed")
    ap.add_argument("--json", default=None, help="--speed: result JSON (default results/)")
    args = ap.parse_args()
    if args.speed:
        from benchmarks._result import write_result

        sizes = [tuple(int(x) for x in z.split("x")) for z in args.sizes.split(",")]
        pitches = [float(p) for p in args.pitches.split(",")]
        res = speed(args.device, sizes, args.repeat, pitches, cpu_check=True)  # type: ignore[arg-type]
        write_result(args.json, "dense_speed", res)
        return
    w, h = (int(x) for x in args.size.split("x"))
    t0 = time.perf_counter()
    pair = render_pair((w, h), args.scenario)
    print(f"rendered {w}x{h} pair in {time.perf_counter() - t0:.1f} s")
    sp, res = sparse_score(pair)
    print("sparse points (own reconstruction):", {k: round(v, 3) for k, v in sp.items()})
    extra = {}
    for kv in args.set:
        k, v = kv.split("=")
        typ = type(getattr(DenseHeightConfig(), k))
        extra[k] = typ(v) if typ is not bool else v.lower() in ("1", "true", "yes")
    for init in args.inits.split(","):
        cfg = dataclasses.replace(DenseHeightConfig(), init=init, **extra)  # type: ignore[arg-type]
        geoms = [("true", (pair.R, pair.t, pair.plane))]
        if res.ok:
            geoms.append(("estimated", (res.R_b_from_a, res.t_b_from_a_m, res.plane)))
        for geom, (R, t, plane) in geoms:
            times = []
            for _ in range(args.repeat):
                dh = dense_height(
                    pair.img_a, pair.img_b, pair.camera, R, t, plane, cfg=cfg, device=args.device
                )
                times.append(dh.timings_s["total"])
            sc = score(dh, pair, geom == "estimated", cfg.window_px)
            print(
                f"dense init={init} geometry={geom}: "
                + ", ".join(f"{k}={v:.3f}" for k, v in sc.items())
                + f", s/pair={np.median(times):.3f} ({dh.timings_s})"
            )


if __name__ == "__main__":
    main()
