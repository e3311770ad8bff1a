"""The cheap two-view probe (reconstruction.probe): tracked corners through the same estimator
chain as a full pair. It must be metric, see the depth a full pair sees, fail with a status
(never raise) on bad frames, and cache its results for a resumed run."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

import roadsurf.reconstruction.probe as probe
from roadsurf.core.camera import Camera
from roadsurf.core.geometry import rotation_from_euler_xyz
from roadsurf.io.drive import Drive, Frame
from roadsurf.io.runfolder import RunFolder
from roadsurf.reconstruction.api import reconstruct_pair
from roadsurf.reconstruction.config import FeatureConfig, ReconstructionConfig
from roadsurf.reconstruction.types import STATUS_FAILED
from tests.reconstruction.conftest import texture

CFG = ReconstructionConfig(features=FeatureConfig(max_features=1500))


def render_surface(
    cam: Camera,
    tex: np.ndarray,
    gsd_m: float,
    depth_m,
    R: np.ndarray = np.eye(3),
    t_m: np.ndarray = np.zeros(3),
) -> np.ndarray:
    """Ray-cast image of the road Z = h + depth(X, Y) (camera a frame, Z down) seen by a camera
    with X_cam = R X_a + t; ``tex`` (H, W) uint8 is the road's albedo at ``gsd_m`` per pixel,
    centred under camera a."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    rays = np.linalg.inv(cam.K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    d = R.T @ rays  # ray directions in frame a
    c = -R.T @ np.asarray(t_m, float)  # camera centre in frame a
    s = (cam.height_m - c[2]) / d[2]
    for _ in range(4):  # fixed point onto the relief
        x, y = c[0] + s * d[0], c[1] + s * d[1]
        s = (cam.height_m + depth_m(x, y) - c[2]) / d[2]
    x, y = c[0] + s * d[0], c[1] + s * d[1]
    mx = (x / gsd_m + tex.shape[1] / 2).reshape(cam.height, cam.width).astype(np.float32)
    my = (y / gsd_m + tex.shape[0] / 2).reshape(cam.height, cam.width).astype(np.float32)
    return cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _rut(depth: float, half_width: float = 0.1, centre_y: float = -0.15):
    """A trough along x, ``depth`` deep (m, positive = below the road), cosine profile."""

    def f(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r = np.abs(y - centre_y) / half_width
        return np.where(r < 1, depth * 0.5 * (1 + np.cos(np.pi * np.minimum(r, 1))), 0.0)

    return f


@pytest.fixture
def scene():
    cam = Camera(512, 384, 480.0, 480.0, 256.0, 192.0, 1.1, 10.0)
    tex = texture((1400, 1400), 7)
    return cam, tex, 1.1 / 480.0  # about one texture pixel per image pixel


def _pair(scene, depth_m, t=(0.0, 0.25, 0.0), euler=(0.3, -0.2, 0.5)):
    cam, tex, gsd = scene
    R = rotation_from_euler_xyz(*np.radians(euler))
    a = render_surface(cam, tex, gsd, depth_m)
    b = render_surface(cam, tex, gsd, depth_m, R, np.asarray(t))
    return a, b


def test_flat_road_probe_is_metric_and_flat(scene) -> None:
    cam = scene[0]
    a, b = _pair(scene, lambda x, y: 0.0 * x)
    res = probe.probe_pair(a, b, cam, CFG)
    assert res.ok, res.reason
    assert res.n_points > 300 and res.config_name == "probe"
    assert abs(np.median(res.points_cam_a_m[:, 2]) - cam.height_m) < 0.01
    np.testing.assert_allclose(res.t_b_from_a_m, [0.0, 0.25, 0.0], atol=0.01)
    assert np.percentile(np.abs(res.plane_dist_m), 99) < 0.003
    assert res.timings_s["tracking"] > 0
    # colour frames work the same (converted to grey)
    rgb = probe.probe_pair(np.dstack([a] * 3), np.dstack([b] * 3), cam, CFG)
    assert rgb.ok and rgb.n_points == res.n_points


def test_probe_sees_the_depth_a_full_pair_sees(scene) -> None:
    """A 20 mm rut: the probe and the full SIFT pair both put points 10 mm below the road,
    and agree on the depth to a few mm; a 3 mm dip stays below 5 mm in both."""
    cam = scene[0]
    a, b = _pair(scene, _rut(0.020))
    pr = probe.probe_pair(a, b, cam, CFG)
    full = reconstruct_pair(a, b, cam, CFG)
    assert pr.ok and full.ok, (pr.reason, full.reason)
    deep_p = pr.plane_dist_m < -0.010
    deep_f = full.plane_dist_m < -0.010
    assert deep_p.sum() >= 20 and deep_f.sum() >= 20
    # the probe sees the trough where it is (|y + 0.15| < 0.1 m in camera a)
    assert np.all(np.abs(pr.points_cam_a_m[deep_p, 1] + 0.15) < 0.1)
    assert abs(-pr.plane_dist_m.min() - -full.plane_dist_m.min()) < 0.004
    shallow, shallow_b = _pair(scene, _rut(0.003))
    ps = probe.probe_pair(shallow, shallow_b, cam, CFG)
    assert ps.ok and int((ps.plane_dist_m < -0.005).sum()) <= 1


def test_bad_frames_give_a_status_not_an_exception(scene) -> None:
    cam, tex, _ = scene
    flat = np.full((cam.height, cam.width), 128, np.uint8)
    res = probe.probe_pair(flat, flat.copy(), cam, CFG)
    assert res.status in STATUS_FAILED and "coarse alignment" in res.reason
    a = texture((cam.height, cam.width), 1)
    b = texture((cam.height, cam.width), 2)  # two different pieces of road
    res = probe.probe_pair(a, b, cam, CFG)
    assert not res.ok and res.status in STATUS_FAILED and res.reason
    with pytest.raises(ValueError, match="differ in size"):
        probe.probe_pair(a, b[:100], cam, CFG)


def test_probe_stage_caches_resumes_and_reports_unreadable_frames(
    scene, tmp_path: Path, monkeypatch
) -> None:
    cam, tex, gsd = scene
    root = tmp_path / "d"
    (root / "frames").mkdir(parents=True)
    frames = []
    for i in range(4):
        img = render_surface(cam, tex, gsd, lambda x, y: 0.0 * x, t_m=np.array([0, -0.2 * i, 0]))
        p = root / "frames" / f"{i:03d}.png"
        if i == 3:
            p.write_bytes(b"\x89PNG not really")
        else:
            cv2.imwrite(str(p), img)
        frames.append(Frame(i, p.name, p, float(i)))
    drive = Drive(root, cam, frames, None, None)
    run_dir = tmp_path / "run"
    res = probe.run(CFG, drive, run_dir, {(0, 1), (2, 3)})
    assert [(r.index_a, r.index_b, r.frame_a) for r in res] == [
        (0, 1, "000.png"),
        (2, 3, "002.png"),
    ]
    assert res[0].ok, res[0].reason
    assert res[1].status == "unreadable_frame" and "003.png" in res[1].reason
    assert len(list(RunFolder(run_dir).probes_dir.glob("*.npz"))) == 2
    calls = []
    orig = probe.probe_pair
    monkeypatch.setattr(probe, "probe_pair", lambda *a, **k: calls.append(1) or orig(*a, **k))
    again = probe.run(CFG, drive, run_dir, {(0, 1), (1, 2)})
    assert len(calls) == 1  # (0, 1) came from RUN/probes
    np.testing.assert_allclose(again[0].points_cam_a_m, res[0].points_cam_a_m)
    assert again[1].ok and again[1].index_a == 1
    with pytest.raises(ValueError, match="frames this drive does not have"):
        probe.run(CFG, drive, run_dir, {(3, 4)})
    # a frame of another size fails that probe (the fused run then makes it a full pair)
    cv2.imwrite(str(root / "frames" / "001.png"), np.zeros((100, 100), np.uint8))
    odd = probe.run(ReconstructionConfig(overwrite=True), drive, run_dir, {(1, 2)})
    assert odd[0].status == "geometry_failed" and "differ in size" in odd[0].reason


def test_probe_cache_is_keyed_by_images_and_settings(scene, tmp_path: Path, monkeypatch) -> None:
    """A probe is reused only while its pair_fingerprint (estimator settings, camera, both
    image files) still matches; a changed image or estimator setting recomputes it."""
    cam, tex, gsd = scene
    root = tmp_path / "d"
    (root / "frames").mkdir(parents=True)
    frames = []
    for i in range(2):
        img = render_surface(cam, tex, gsd, lambda x, y: 0.0 * x, t_m=np.array([0, -0.2 * i, 0]))
        p = root / "frames" / f"{i:03d}.png"
        cv2.imwrite(str(p), img)
        frames.append(Frame(i, p.name, p, float(i)))
    drive = Drive(root, cam, frames, None, None)
    run_dir = tmp_path / "run"
    probe.run(CFG, drive, run_dir, {(0, 1)})
    stored = list(RunFolder(run_dir).probes_dir.glob("*.fingerprint"))
    assert len(stored) == 1 and stored[0].with_suffix(".npz").is_file()
    calls = []
    orig = probe.probe_pair
    monkeypatch.setattr(probe, "probe_pair", lambda *a, **k: calls.append(1) or orig(*a, **k))
    probe.run(CFG, drive, run_dir, {(0, 1)})
    assert calls == []  # unchanged: reused
    # an estimator setting outside ``cfg.probe`` (not in the file name) recomputes it
    other = ReconstructionConfig(features=FeatureConfig(max_features=1500), min_matches=25)
    probe.run(other, drive, run_dir, {(0, 1)})
    assert len(calls) == 1
    probe.run(other, drive, run_dir, {(0, 1)})
    assert len(calls) == 1  # ... and is reused under the new settings
    # a re-rendered frame recomputes it
    img = cv2.imread(str(frames[1].path), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(frames[1].path), np.ascontiguousarray(img[:, ::-1]))
    res = probe.run(other, drive, run_dir, {(0, 1)})
    assert len(calls) == 2 and res[0].index_b == 1
    probe.run(other, drive, run_dir, {(0, 1)})
    assert len(calls) == 2
    assert len(list(RunFolder(run_dir).probes_dir.glob("*"))) == 2  # one probe, one fingerprint
