"""The image a pair's dense heights are measured on (mapping.dense_refimage): the nearer one for
a camera tilted forward, image a for a nadir camera or a backward drive; heights measured on
image b of a seeded tilted pair agree with the exact height field and reach image b's own side
borders, and a rolling-shutter pair measured on image b (its time first) stays level."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from benchmarks.dense import synthetic_pair
from roadsurf.core.camera import Camera
from roadsurf.core.geometry import vehicle_from_cam_rotation, world_from_vehicle_rotation
from roadsurf.io.drive import load_drive, read_gray
from roadsurf.mapping.dense_refimage import reference_is_b, reversed_pair
from roadsurf.reconstruction.api import reconstruct_pair
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.dense.config import DenseHeightConfig
from roadsurf.reconstruction.dense.parallax import dense_height
from roadsurf.simulation.scenarios import simulate

CAM = Camera(320, 240, 300.0, 300.0, 159.5, 119.5, 1.1, 15.0)


def _poses(pitch_deg: float, forward_m: float) -> tuple[np.ndarray, np.ndarray]:
    """world_from_cam (4, 4) of two frames heading north, 1.1 m up, b ``forward_m`` ahead."""
    W = np.eye(4)
    W[:3, :3] = world_from_vehicle_rotation(0.0) @ vehicle_from_cam_rotation(pitch_deg, 0.0, 0.0)
    W[:3, 3] = [0.0, 0.0, 1.1]
    Wb = W.copy()
    Wb[1, 3] += forward_m
    return W, Wb


@pytest.mark.parametrize(
    ("pitch_deg", "forward_m", "want"),
    [
        (30.0, 0.35, True),
        (45.0, 0.4, True),
        (0.0, 0.35, False),
        (1.0, 0.35, False),  # a nadir camera pitched by the vehicle keeps image a
        (-1.0, 0.35, False),
        (30.0, -0.35, False),
    ],
)
def test_the_nearer_image_is_b_only_for_a_forward_tilted_drive(
    pitch_deg: float, forward_m: float, want: bool
) -> None:
    assert reference_is_b(CAM, *_poses(pitch_deg, forward_m)) is want


def test_a_rolling_shutter_pair_measured_on_image_b_stays_level(tmp_path: Path) -> None:
    """A flat road, 6 m/s at 15 fps with a 30 ms readout, matched on image b (b's time first:
    a negative frame time difference): each row read at its own pose keeps the heights level;
    read at the timestamps they drift (tests/reconstruction/test_dense_rolling.py's pair)."""
    drive = load_drive(
        simulate(
            "flat",
            tmp_path / "rs",
            n_frames=2,
            progress=False,
            readout_s=0.03,
            width=320,
            height=240,
            fx=300.0,
            unevenness_m=0.0,
            undulation_m=0.0,
        )  # fmt: skip
    )
    a, b = drive.frames
    res = reconstruct_pair(a, b, drive.camera, ReconstructionConfig())
    assert res.ok, res.reason
    R_ab, t_ab, plane_b = reversed_pair(res)
    spread = {}
    for rows in (True, False):
        dt = (a.timestamp_s - b.timestamp_s) if rows else None
        dh = dense_height(
            read_gray(b), read_gray(a), drive.camera, R_ab, t_ab, plane_b,
            cfg=DenseHeightConfig(device="cpu"), frame_dt_s=dt,
        )  # fmt: skip
        h = dh.height_m[dh.valid]
        assert dh.valid.mean() > (0.3 if rows else 0.0)  # at the timestamps most pixels fail
        spread[rows] = float(1.4826 * np.median(np.abs(h - np.median(h))))
    # measured: 1.2 mm with the rows (on image a 1.2 mm), 58 mm at the timestamps (on a 50 mm)
    assert spread[True] < 0.003
    assert spread[True] < 0.2 * spread[False]


def test_heights_measured_on_image_b_match_the_truth() -> None:
    """The 30° pair matched with b as reference: each valid pixel's point, moved into camera a
    and projected there, reads the exact height (bilinear in a's truth); errors as on image a
    (test_dense_parallax: flat < 2 mm, pothole < 3 mm)."""
    pair = synthetic_pair((320, 240), pitch_deg=30.0, seed=2)
    p = SimpleNamespace(R_b_from_a=pair.R, t_b_from_a_m=pair.t, plane=pair.plane)
    R_ab, t_ab, plane_b = reversed_pair(p)  # type: ignore[arg-type]
    cfg = DenseHeightConfig(device="cpu")
    dh = dense_height(pair.img_b, pair.img_a, pair.camera, R_ab, t_ab, plane_b, cfg=cfg)
    vv, uu = np.nonzero(dh.valid)
    h = dh.height_m[vv, uu].astype(float)
    X_a = dh.model.points_cam_a(h, uu.astype(float), vv.astype(float)) @ R_ab.T + t_ab
    K = pair.camera.K
    q = X_a @ K.T
    u, v = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]

    def at(img: np.ndarray) -> np.ndarray:
        return map_coordinates(img.astype(float), [v, u], order=1, cval=np.nan)

    eta, dep = at(pair.eta_true), at(pair.depth_true)
    err = h - eta
    flat = np.isfinite(err) & (dep <= 0.0)
    pot = np.isfinite(err) & (dep > 0.005)
    assert flat.sum() > 5000 and pot.sum() > 300
    # measured: flat 1.64 mm, pothole 2.06 mm (on image a: 1.42 / 2.17 mm, scored on its grid)
    assert float(np.mean(np.abs(err[flat]))) < 0.002
    assert float(np.mean(np.abs(err[pot]))) < 0.003
    # the pothole reads below the road (the plane's side is kept in camera b)
    assert float(np.median(h[pot])) < -0.01


def test_a_pair_measured_on_image_b_reaches_its_side_borders() -> None:
    """With image b as the reference, the two-view part's sides are image b's own first and
    last columns (image a, further back, sees the road wider). Their left-right check needs the
    reverse match (a -> b) there, which starts from the sweep: the sweep pixels past image b's
    border have no match, took the candidate that pulled their window into image b (a ramp of
    parallax, 2-13 px), and the upsampling carried it up to a sweep pixel (4 px) into the
    overlap. Before the fix the three outermost columns kept 18 % (left) and 16 % (right) of
    their pixels on this pair (the map: a 2-4 cell strip along the two-view part's edge); now
    99 / 100 %."""
    pair = synthetic_pair((320, 240), pitch_deg=30.0, seed=2)
    p = SimpleNamespace(R_b_from_a=pair.R, t_b_from_a_m=pair.t, plane=pair.plane)
    R_ab, t_ab, plane_b = reversed_pair(p)  # type: ignore[arg-type]
    cfg = DenseHeightConfig(device="cpu")
    dh = dense_height(pair.img_b, pair.img_a, pair.camera, R_ab, t_ab, plane_b, cfg=cfg)
    h = dh.shape[0]
    rows = slice(h // 3, h - 10)  # image b's lower two thirds: inside image a's view
    left, right = dh.valid[rows, :3].mean(), dh.valid[rows, -3:].mean()
    assert left > 0.9 and right > 0.9, (left, right)
