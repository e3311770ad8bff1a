"""Ground size of pixels where detection turns pixels into metres (detection/gsd.py): per pixel
for a tilted camera, the nominal value for a nadir one (bit for bit)."""

import cv2
import numpy as np
import pytest

from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackfilter import thin_dark_components
from roadsurf.detection.gsd import NadirView, ground_px_m_raw
from roadsurf.io.drive import Camera


def _camera(pitch_deg: float, yaw_deg: float = 0.0, dist=(0.0,) * 5) -> Camera:
    return Camera(
        width=320, height=240, fx=300.0, fy=300.0, cx=159.5, cy=119.5, height_m=0.5, fps=10.0,
        dist=tuple(dist), mount_deg=(pitch_deg, 0.0, yaw_deg),
    )  # fmt: skip


def _road_px(cam: Camera, xy: np.ndarray) -> np.ndarray:
    """Ideal pixels of road points (vehicle frame x right, y backward; road z = height_m)."""
    X = np.c_[xy, np.full(len(xy), cam.height_m)] @ cam.vehicle_from_cam  # cam = R^T X_vehicle
    return (X @ cam.K.T)[:, :2] / X[:, 2:3]


@pytest.mark.parametrize("yaw_deg", [0.0, 7.0])
def test_nadir_view_of_a_nadir_camera_is_the_image_itself(yaw_deg):
    cam = _camera(0.0, yaw_deg)
    v = NadirView(cam)
    px = np.array([[3.25, 7.5], [300.0, 200.0]])
    assert v.nadir and v.px(px) is not None and np.array_equal(v.px(px), px)
    assert v.m_per_px == cam.ground_px_m()


def test_nadir_view_of_a_tilted_camera_has_one_scale():
    """A 45° camera: a 1 cm grid on the road lands in the nadir view 1 cm / m_per_px apart,
    near the camera and far from it, although the image itself compresses the far road."""
    cam = _camera(45.0)
    v = NadirView(cam)
    g = np.arange(-0.1, 0.1001, 0.01)
    for y0 in (-0.3, -0.8):  # near and far (vehicle y points backward: ahead is negative)
        X, Y = np.meshgrid(g, y0 + g)
        px = _road_px(cam, np.c_[X.ravel(), Y.ravel()])
        q = v.px(px).reshape(len(g), len(g), 2)
        step = np.linalg.norm(np.diff(q, axis=1), axis=2)
        assert step == pytest.approx(0.01 / v.m_per_px, rel=1e-6)


def test_ground_px_of_a_tilted_camera_grows_towards_the_horizon():
    cam = _camera(45.0, dist=(-0.1, 0.0, 0.0, 0.0, 0.0))
    near, far = ground_px_m_raw(cam, np.array([[160.0, 235.0], [160.0, 5.0]]), 0.001)
    assert far > 2.5 * near
    nadir = _camera(0.0)
    g = ground_px_m_raw(nadir, np.array([[0.0, 0.0], [160.0, 120.0]]), 0.001)
    assert np.all(g == nadir.ground_px_m())
    # above the horizon: the fallback
    up = _camera(80.0)
    assert ground_px_m_raw(up, np.array([[160.0, 0.0]]), 0.123)[0] == 0.123


def test_crack_pieces_are_judged_in_metres_at_their_own_pixels():
    """Two identical dark lines, 60 px long: where a pixel covers 3 mm of road the piece is
    18 cm long, a crack piece; where it covers 1 mm (nearer a tilted camera), 6 cm, shorter than
    min_length_m (8 cm). With one nominal 3 mm/px both would pass."""
    img = np.full((240, 320), 140, np.uint8)
    rng = np.random.default_rng(0)
    img = np.clip(img + rng.normal(0, 6, img.shape), 0, 255).astype(np.uint8)
    for v in (40, 200):
        cv2.line(img, (130, v), (190, v), 60, 2)

    def gsd_at(px: np.ndarray) -> np.ndarray:
        return np.where(np.asarray(px)[:, 1] < 120, 0.003, 0.001)

    lab, keep, widths, gsd = thin_dark_components(img, 0.003, CrackConfig(), gsd_at)
    rows = [float(np.nonzero(lab == i)[0].mean()) for i in keep]
    assert len(keep) == 1 and rows[0] < 120 and gsd[0] == 0.003
    assert widths[0] * gsd[0] < CrackConfig().max_width_m
    assert len(thin_dark_components(img, 0.003, CrackConfig())[1]) == 2


def _pair_with_deep_patch(cam: Camera, y0: float):
    """A pair of a 45° camera whose points sample the road on a 1 cm grid, with a 6 x 6 cm
    patch 2 cm deep at vehicle y0 (ahead: negative)."""
    from roadsurf.detection.pairs import PairDefects
    from roadsurf.reconstruction.types import PairResult

    g = np.arange(-0.3, 0.3, 0.01)
    X, Y = np.meshgrid(g, np.arange(-1.2, 0.0, 0.01))
    xy = np.c_[X.ravel(), Y.ravel()]
    px = _road_px(cam, xy)
    inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    xy, px = xy[inside], px[inside]
    deep = (np.abs(xy[:, 0]) < 0.03) & (np.abs(xy[:, 1] - y0) < 0.03)
    dist = np.where(deep, -0.02, 0.0)
    n = len(xy)
    pair = PairResult(
        frame_a="a.png", frame_b="b.png", index_a=0, index_b=1, method="proposed",
        status="ok", points_cam_a_m=np.zeros((n, 3)), px_a=px, px_b=px + 1000.0,
    )  # fmt: skip
    pd = PairDefects(
        index_a=0, frame_a="a.png", candidate=deep, refined=deep, dist_m=dist,
        threshold_m=0.008, noise_m=0.001, deep_area_m2=0.0, score=0.0, area_per_point_m2=1e-4,
    )  # fmt: skip
    return pair, pd, int(deep.sum())


@pytest.mark.parametrize("y0", [-0.35, -0.9])
def test_pair_frame_decision_measures_the_deep_area_in_metres_on_a_tilted_camera(y0):
    """The per-pair frame decision bins the deep points on the nadir view: a 36 cm² patch
    reads 36 cm² near the camera and far from it (in the image, far pixels cover ~2x more
    road than near ones)."""
    from roadsurf.detection.config import DetectionConfig
    from roadsurf.detection.framelabels import pair_frame_scores
    from roadsurf.io.drive import Drive, Frame

    cam = _camera(45.0)
    pair, pd, n_deep = _pair_with_deep_patch(cam, y0)
    assert n_deep == 36
    drive = Drive(None, cam, [Frame(0, "a.png", None, 0.0)], gps=None, obd=None)
    cfg = DetectionConfig()
    p = pair_frame_scores(cfg, drive, [pair], {0: pd})["a.png"]
    area = p * cfg.map.frame_min_area_m2 / (1 - p)
    assert area == pytest.approx(0.0036, rel=0.35)
