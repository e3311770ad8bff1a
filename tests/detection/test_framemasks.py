"""Frame views of the map's defects (detection/framemasks.py): masks, frame labels and the frames
each defect lists come from one projection through each frame's pose, so they agree; the
projection is right for nadir and tilted cameras, with lens distortion."""

import cv2
import numpy as np
import pytest

from roadsurf.core.geometry import vehicle_from_cam_rotation, world_from_cam
from roadsurf.detection import stage
from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.framemasks import DefectCells, FrameProjector, frame_mask, frame_views
from roadsurf.detection.mapframe import MapFrame
from roadsurf.io.drive import Camera
from roadsurf.io.formats import read_csv
from roadsurf.mapping.types import Trajectory
from tests.detection.synthetic import REF, Pothole, Scene, build

CFG = DetectionConfig()


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / max(int((a | b).sum()), 1)


def _disc_cells(cx: float, cy: float, r: float, gsd: float) -> np.ndarray:
    g = np.arange(-r, r + gsd, gsd)
    X, Y = np.meshgrid(cx + g, cy + g)
    inside = (X - cx) ** 2 + (Y - cy) ** 2 <= r * r
    return np.c_[X[inside], Y[inside]]


def _ray_cast_disc(camera: Camera, T: np.ndarray, cx, cy, r, road_z) -> np.ndarray:
    """Reference: every pixel's ray (through the lens) meets the road z = road_z inside the disc."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(float)
    n = camera.normalised_from_raw_px(np.c_[u.ravel(), v.ravel()])
    rays = np.c_[n, np.ones(len(n))] @ T[:3, :3].T
    s = (road_z - T[2, 3]) / rays[:, 2]
    x, y = T[0, 3] + s * rays[:, 0], T[1, 3] + s * rays[:, 1]
    hit = (s > 0) & ((x - cx) ** 2 + (y - cy) ** 2 <= r * r)
    return hit.reshape(camera.height, camera.width)


@pytest.mark.parametrize(
    ("pitch_deg", "dist", "disc_xy"),
    [
        (0.0, (0.0, 0.0, 0.0, 0.0, 0.0), (0.15, 0.08)),
        (45.0, (0.0, 0.0, 0.0, 0.0, 0.0), (0.03, 0.5)),
        (45.0, (-0.2, 0.05, 0.0, 0.0, 0.0), (0.25, 0.7)),  # off-centre: the lens bends it
    ],
)
def test_cells_are_drawn_where_the_frame_sees_them(pitch_deg, dist, disc_xy):
    """A disc of 5 mm cells on the road, projected into a nadir and a 45° camera (one with
    barrel distortion), covers the pixels whose rays hit the disc (ray-cast reference)."""
    cam = Camera(
        width=320, height=240, fx=300.0, fy=300.0, cx=159.5, cy=119.5, height_m=0.5, fps=10.0,
        dist=dist, mount_deg=(pitch_deg, 0.0, 0.0),
    )  # fmt: skip
    T = world_from_cam(0.0, position_enu_m=np.array([0.0, 0.0, 0.5]))
    T[:3, :3] = T[:3, :3] @ vehicle_from_cam_rotation(pitch_deg, 0.0, 0.0)
    (cx, cy), r = disc_xy, 0.08
    cells = DefectCells(_disc_cells(cx, cy, r, 0.005), np.zeros((0, 2)), 0.005)
    mask = frame_mask(cam, T, np.array([0.0, 0.0, 0.0]), MapFrame.create(None), [cells])
    ref = _ray_cast_disc(cam, T, cx, cy, r, 0.0)
    assert ref.sum() > 500
    assert _iou(mask, ref) > 0.9


def test_deep_area_counts_only_what_the_image_sees():
    """frame_views: deep cells fully inside the image count in full, half outside in half, and
    a defect outside the view is not seen at all."""
    cam = Camera(width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5, height_m=1.0, fps=10)
    T = world_from_cam(0.0, position_enu_m=np.array([0.0, 0.0, 1.0]))
    traj = Trajectory(
        filenames=["a.png"], frame_indices=np.arange(1), timestamp_s=np.zeros(1),
        world_from_cam=T[None], source=["gps"], reference=None,
    )  # fmt: skip
    half_w = 0.5 * 160 / 150.0  # the footprint's half width (m)
    inside = DefectCells(np.zeros((0, 2)), _disc_cells(0.0, 0.0, 0.1, 0.005), 0.005)
    edge = DefectCells(np.zeros((0, 2)), _disc_cells(half_w, 0.0, 0.1, 0.005), 0.005)
    away = DefectCells(_disc_cells(3.0, 0.0, 0.1, 0.005), np.zeros((0, 2)), 0.005)
    views = frame_views(cam, traj, MapFrame.create(None), ["a.png"], {}, [inside, edge, away], {})
    v = views["a.png"]
    full = len(inside.deep_xy_m) * 0.005**2
    assert v.defects == [0, 1]
    assert v.deep_area_m2 == pytest.approx(1.5 * full, rel=0.05)


def test_projector_rejects_points_behind_and_beyond_the_lens():
    cam = Camera(
        width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5, height_m=1.0, fps=10,
        dist=(-0.3, 0.1, 0.0, 0.0, 0.0),
    )  # fmt: skip
    T = world_from_cam(0.0, position_enu_m=np.array([0.0, 0.0, 1.0]))
    proj = FrameProjector(cam, T, None, MapFrame.create(None))
    # far beyond the field of view: a distortion polynomial would fold it back into the image
    assert not proj.inside(np.array([[30.0, 0.0], [0.0, 30.0]])).any()
    assert proj.inside(np.array([[0.0, 0.0]])).all()


def test_projector_uses_each_row_s_pose_with_a_rolling_shutter():
    """With readout_s and the frame's motion the cells land where core.rolling puts them (the
    row that exposed them); without a readout the motion is ignored."""
    import dataclasses

    from roadsurf.core.rolling import raw_px_from_world

    cam = Camera(
        width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5, height_m=1.0, fps=30,
        readout_s=0.02,
    )  # fmt: skip
    T = world_from_cam(0.0, position_enu_m=np.array([0.0, 0.0, 1.0]))
    mf = MapFrame.create(None)
    motion = (np.array([0.0, 25.0, 0.0]), np.zeros(3))
    xy = np.array([[0.1, 0.2], [-0.2, -0.1], [0.0, 0.3]])
    uv, ok = FrameProjector(cam, T, None, mf, motion).project(xy)
    enu = mf.enu_from_grid(xy)
    u, v = raw_px_from_world(cam, np.c_[enu, np.zeros(len(enu))], T, *motion)
    assert ok.all()
    np.testing.assert_allclose(uv, np.c_[u, v], atol=1e-9)
    still, _ = FrameProjector(cam, T, None, mf).project(xy)
    assert np.abs(still - uv).max() > 5.0  # 0.5 m during readout: tens of pixels
    gs = dataclasses.replace(cam, readout_s=0.0)
    np.testing.assert_array_equal(
        FrameProjector(gs, T, None, mf, motion).project(xy)[0],
        FrameProjector(gs, T, None, mf).project(xy)[0],
    )


def test_every_frame_of_an_ok_pair_gets_a_mask_that_agrees_with_labels_and_defects(tmp_path):
    """Frames a and b of every ok pair get a mask; a defect frame's mask is not empty and shows
    the defects that list it; a frame no defect lists has an empty mask. The pothole's mask
    covers its part deeper than T_d, projected with the true pose."""
    pot = Pothole(0.1, 1.0, 0.15, 0.030)
    drive, pairs, traj = build(Scene(potholes=[pot], lane_x_m=-0.3), tmp_path / "drive")
    run_dir = tmp_path / "run"
    res = stage.run(CFG, drive, pairs, traj, run_dir)
    assert len(res.defects) == 1
    masks = {}
    for f in drive.frames:
        p = run_dir / "masks" / f"{f.filename.rsplit('.', 1)[0]}.png"
        assert p.is_file(), f.filename  # 6 frames, all in an ok pair (b of the last one too)
        m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert m.dtype == np.uint8 and m.shape == (drive.camera.height, drive.camera.width)
        masks[f.filename] = m > 0
    flagged = {r["filename"] for r in read_csv(run_dir / "frames.csv") if r["defect"] == "1"}
    shown = {fn for fn, m in masks.items() if m.any()}
    assert flagged == {"000002.png", "000003.png"}
    assert flagged <= shown and set(res.defects[0].frames) == shown
    # the part deeper than T_d (8 mm) of the 30 mm bowl: r sqrt(1 - 8 / 30)
    r_td = pot.radius_m * np.sqrt(1 - 0.008 / pot.depth_m)
    for fn in flagged:
        T = traj.world_from_cam[traj.filenames.index(fn)]
        ref = _ray_cast_disc(drive.camera, T, pot.x_m, pot.y_m, r_td, 0.0)
        assert _iou(masks[fn], ref) > 0.7, fn


def test_no_gps_run_writes_masks_in_the_local_frame(tmp_path):
    drive, pairs, traj = build(
        Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.030)]), tmp_path / "drive", georeferenced=False
    )
    res = stage.run(CFG, drive, pairs, traj, tmp_path / "run")
    m = cv2.imread(str(tmp_path / "run" / "masks" / "000002.png"), cv2.IMREAD_UNCHANGED)
    assert len(res.defects) == 1 and (m > 0).sum() > 100


def test_enu_from_grid_inverts_grid_from_enu():
    mf = MapFrame.create(REF)
    enu = np.array([[0.0, 0.0, 0.0], [12.3, -40.0, 0.0], [-250.0, 310.0, 0.0]])
    back = mf.enu_from_grid(mf.grid_from_enu(enu))
    assert back == pytest.approx(enu[:, :2], abs=1e-4)


def _reference_mask(cam: Camera, T: np.ndarray, cells: list[DefectCells]) -> np.ndarray:
    """frame_mask as first written: every listed cell (repeats too) projected and drawn."""
    mask = np.zeros((cam.height, cam.width), np.uint8)
    proj = FrameProjector(cam, T, np.array([0.0, 0.0, 0.0]), MapFrame.create(None))
    for c in cells:
        xy = np.vstack([c.mask_xy_m, c.deep_xy_m])
        h = 0.5 * c.gsd_m
        offs = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
        uv, ok = proj.project((xy[:, None, :] + offs[None]).reshape(-1, 2))
        uv, ok = uv.reshape(-1, 4, 2), ok.reshape(-1, 4).all(axis=1)
        ok &= (uv[:, :, 0].max(axis=1) >= -1) & (uv[:, :, 0].min(axis=1) <= cam.width)
        ok &= (uv[:, :, 1].max(axis=1) >= -1) & (uv[:, :, 1].min(axis=1) <= cam.height)
        for q in np.round(uv[ok] * 4.0).astype(np.int32):
            cv2.fillConvexPoly(mask, q, 1, lineType=cv2.LINE_8, shift=2)
    return mask.astype(bool)


def test_mask_draws_each_cell_once_and_matches_drawing_every_listed_cell():
    """A defect's deep cells repeat its mask cells: frame_mask draws each distinct cell once,
    and the mask is pixel for pixel the one drawing every listed cell gives (45° camera with
    a lens distortion, cells partly off the image)."""
    from roadsurf.detection.framemasks import _distinct_rows

    cam = Camera(
        width=320, height=240, fx=300.0, fy=300.0, cx=159.5, cy=119.5, height_m=0.5, fps=10.0,
        dist=(-0.2, 0.05, 0.0, 0.0, 0.0), mount_deg=(45.0, 0.0, 0.0),
    )  # fmt: skip
    T = world_from_cam(0.0, position_enu_m=np.array([0.0, 0.0, 0.5]))
    T[:3, :3] = T[:3, :3] @ vehicle_from_cam_rotation(45.0, 0.0, 0.0)
    rng = np.random.default_rng(4)
    cells = []
    for cx, cy in [(0.05, 0.5), (0.6, 0.9), (-0.9, 0.3)]:  # the last one mostly off the image
        xy = _disc_cells(cx, cy, 0.15, 0.005)
        deep = xy[rng.random(len(xy)) < 0.6]  # deeper cells: the same lattice centres
        cells.append(DefectCells(xy, deep, 0.005))
    stacked = np.vstack([cells[0].mask_xy_m, cells[0].deep_xy_m])
    distinct = _distinct_rows(stacked)
    assert len(distinct) == len(cells[0].mask_xy_m)
    np.testing.assert_array_equal(distinct, cells[0].mask_xy_m)  # first order kept
    mask = frame_mask(cam, T, np.array([0.0, 0.0, 0.0]), MapFrame.create(None), cells)
    ref = _reference_mask(cam, T, cells)
    assert ref.sum() > 1000 and not ref.all()
    np.testing.assert_array_equal(mask, ref)
