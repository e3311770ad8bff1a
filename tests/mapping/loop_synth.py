"""A seeded revisit: the same lane driven twice (a survey that comes back), for the loop tests.

Pass 1 and pass 2 follow the same straight road 10 cm apart, 20 s apart in time, with no pair
between them (a new segment: only GPS ties the passes). The GPS has a different slow bias on
each pass (consumer grade: σ 0.3 m, bias ±0.4 m), so without a loop constraint the two passes
are placed decimetres apart. ``match(i, j)`` plays the reconstruction's pair API for any two
frames: the true keypoints both see, with pixel noise and a pair-sized pose error.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.core.geometry import invert_pose, world_from_cam
from roadsurf.io.drive import Drive
from roadsurf.reconstruction.types import PairResult
from tests.mapping.bundle_synth import gps_from_enu, synthetic_drive
from tests.mapping.synth import camera


@dataclass
class Revisit:
    drive: Drive
    pairs: list[PairResult]  # consecutive pairs within each pass
    world_from_cam: np.ndarray  # (2n, 4, 4) true poses
    n: int  # frames per pass
    match: Callable[[int, int], PairResult | None]  # the pair API on frames i, j


def make_revisit(n: int = 30, seed: int = 0, speed_mps: float = 4.0, fps: float = 10.0) -> Revisit:
    rng = np.random.default_rng(seed)
    cam = camera(width=320, height=240, fps=fps)
    dt = 1.0 / fps
    W = np.empty((2 * n, 4, 4))
    t = np.empty(2 * n)
    for p, (x_off, t0) in enumerate(((0.0, 0.0), (0.1, n * dt + 20.0))):
        for k in range(n):
            roll, pitch = np.radians(rng.normal(0, 0.3, 2))
            pos = np.array([x_off, speed_mps * dt * k, 1.0])
            W[p * n + k] = world_from_cam(0.0, roll, pitch, pos)
            t[p * n + k] = t0 + k * dt
    L = speed_mps * dt * n
    npts = int(150 * 2.0 * (L + 2.0))
    pts = np.column_stack(
        [rng.uniform(-1.0, 1.1, npts), rng.uniform(-1.0, L + 1.0, npts), np.zeros(npts)]
    )
    kp: list[dict[int, np.ndarray]] = []
    for i in range(2 * n):
        Xc = (pts - W[i][:3, 3]) @ W[i][:3, :3]
        uv = Xc[:, :2] / Xc[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        vis = (uv[:, 0] > 3) & (uv[:, 0] < cam.width - 4) & (uv[:, 1] > 3)
        vis &= uv[:, 1] < cam.height - 4
        ids = np.flatnonzero(vis)
        kp.append(dict(zip(ids.tolist(), uv[ids] + rng.normal(0, 0.2, (len(ids), 2)), strict=True)))

    def pair(i: int, j: int) -> PairResult | None:
        ids = np.array(sorted(set(kp[i]) & set(kp[j])), int)
        if len(ids) < 30:
            return None
        T = invert_pose(W[j]) @ W[i]
        s = 1.0 + rng.normal(0, 0.005)
        Rn = Rotation.from_rotvec(rng.normal(0, np.radians(0.1), 3)).as_matrix() @ T[:3, :3]
        Xa = s * ((pts[ids] - W[i][:3, 3]) @ W[i][:3, :3])
        A = np.column_stack([Xa[:, 0], Xa[:, 1], np.ones(len(ids))])
        plane, *_ = np.linalg.lstsq(A, Xa[:, 2], rcond=None)
        return PairResult(
            frame_a=f"{i:06d}.png", frame_b=f"{j:06d}.png", index_a=i, index_b=j,
            method="proposed", status="ok", points_cam_a_m=Xa,
            px_a=np.array([kp[i][k] for k in ids]), px_b=np.array([kp[j][k] for k in ids]),
            cov_m2=np.tile(np.eye(3) * 1e-8, (len(ids), 1, 1)), plane_dist_m=np.zeros(len(ids)),
            plane=plane, R_b_from_a=Rn, t_b_from_a_m=s * T[:3, 3] + rng.normal(0, 0.002, 3),
            n_matches=len(ids), n_inliers=len(ids), match_idx=np.arange(len(ids)),
        )  # fmt: skip

    pairs = [p for k in range(2 * n - 1) if k != n - 1 and (p := pair(k, k + 1)) is not None]
    # GPS 1 Hz over both passes, each pass with its own bias
    tg = np.concatenate([np.arange(t[0], t[n - 1] + 1e-9, 1.0), np.arange(t[n], t[-1] + 1e-9, 1.0)])
    C = W[:, :3, 3]
    true_g = np.column_stack([np.interp(tg, t, C[:, k]) for k in range(3)])
    bias = np.where((tg < t[n])[:, None], [0.4, -0.3, 0.0], [-0.4, 0.3, 0.0])
    meas = true_g + bias + rng.normal(0, 0.1, true_g.shape)
    drive = synthetic_drive(cam, t[: 2 * n], gps_from_enu(tg, meas))
    return Revisit(drive, pairs, W, n, pair)
