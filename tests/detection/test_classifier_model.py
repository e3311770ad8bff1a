"""DefectNet, model files, training and screening on small seeded synthetic images."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from roadsurf.core.errors import ModelFileError, RoadsurfError
from roadsurf.core.imagemask import ImageMask
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.modelfile import load_model, save_model
from roadsurf.detection.classifier.network import DefectNet
from roadsurf.detection.classifier.screen import screen_drive, screen_threads
from roadsurf.detection.classifier.screen_job import ScreeningJob
from roadsurf.detection.classifier.train import metrics, train, train_steps
from roadsurf.io.drive import Camera, Drive, Frame


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """CI machines are small and shared: one thread avoids oversubscription stalls."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def road_image(rng: np.random.Generator, defect: bool, size: int = 96) -> np.ndarray:
    """Grey asphalt texture; a defect is a dark blob with a darker core, at a random place."""
    base = rng.uniform(90, 160)
    img = base + rng.normal(0, 10, (size, size))
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    if rng.random() < 0.5:  # a lane marking on some frames of both classes
        x = int(rng.integers(0, size - 8))
        img[:, x : x + 6] += 70
    if defect:
        cx, cy = rng.integers(size // 4, 3 * size // 4, 2)
        r = rng.uniform(0.10, 0.22) * size
        yy, xx = np.mgrid[:size, :size]
        d = np.hypot(xx - cx, yy - cy) / r
        img -= 60 * np.clip(1.0 - d, 0, 1) ** 0.5
    return np.clip(img, 0, 255).astype(np.uint8)


def write_dataset(root: Path, n_per_class: int = 24, size: int = 96, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True)
    with open(root / "labels.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "label", "group", "augmentation"])
        for i in range(2 * n_per_class):
            lab = i % 2
            name = f"images/f{i:03d}.png"
            cv2.imwrite(str(root / name), road_image(rng, bool(lab), size))
            w.writerow([name, lab, f"g{i}", ""])
    return root


def test_network_overfits_a_small_batch() -> None:
    torch.manual_seed(0)
    rng = np.random.default_rng(1)
    x = torch.from_numpy(np.stack([road_image(rng, i % 2 == 1, 64) for i in range(16)]))
    y = torch.tensor([i % 2 for i in range(16)])
    net = DefectNet(64, dropout=0.0)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(0)
    first = train_steps(net, x, y, opt, 1, 16, gen, dihedral=False)
    for _ in range(80):
        last = train_steps(net, x, y, opt, 1, 16, gen, dihedral=False)
    net.eval()
    pred = net.predict_proba(x.unsqueeze(1)).argmax(1)
    assert last < 0.1 * first
    assert (pred == y).all()


def test_forward_rejects_wrong_shape() -> None:
    from roadsurf.core.errors import RoadsurfError

    with pytest.raises(RoadsurfError, match="expects"):
        DefectNet(64)(torch.zeros(2, 1, 32, 32, dtype=torch.uint8))


def test_save_load_round_trip_gives_identical_outputs(tmp_path: Path) -> None:
    torch.manual_seed(3)
    net = DefectNet(64, dropout=0.3).eval()
    save_model(tmp_path / "m", net, {"architecture": {"dropout": 0.3, "width": 1}, "note": 1.5})
    net2, meta = load_model(tmp_path / "m")
    x = torch.randint(0, 256, (5, 1, 64, 64), dtype=torch.uint8)
    assert torch.equal(net(x), net2(x))
    assert meta["class_names"] == ["non-defect", "defect"]
    assert meta["input_size_px"] == 64 and meta["torch_version"] == torch.__version__
    # the bare .safetensors file is self-contained
    net3, _ = load_model(tmp_path / "m" / "model.safetensors")
    assert torch.equal(net(x), net3(x))


def test_test_time_views_make_the_net_orientation_free_and_round_trip(tmp_path: Path) -> None:
    torch.manual_seed(4)
    net = DefectNet(48, dropout=0.0).eval()
    x = torch.randint(0, 256, (3, 1, 48, 48), dtype=torch.uint8)
    turned = torch.flip(torch.rot90(x, 1, dims=(2, 3)), dims=(3,))
    # one view: the plain forward pass, which depends on how the frame is turned
    assert torch.equal(net.logits(x), net(x))
    assert not torch.allclose(net(x), net(turned), atol=1e-4)
    # all eight views: a flipped/turned frame gets the same probability (a road has no 'up')
    net.tta_views = 8
    assert torch.allclose(net.logits(x), net.logits(turned), atol=1e-4)
    assert torch.allclose(net.predict_proba(x), net.predict_proba(turned), atol=1e-5)
    net.temperature = 1.7
    save_model(tmp_path / "m", net, {})
    net2, meta = load_model(tmp_path / "m")
    assert meta["tta_views"] == 8 and net2.tta_views == 8
    assert torch.equal(net.predict_proba(x), net2.predict_proba(x))
    assert ClassifierConfig().tta_views == 8


def test_corrupt_missing_and_incompatible_model_files_give_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ModelFileError, match="not found.*roadsurf train"):
        load_model(tmp_path / "nothing")
    net = DefectNet(64).eval()
    path = save_model(tmp_path / "m", net, {})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(ModelFileError, match="corrupt"):
        load_model(path)
    path.write_bytes(b"\x00garbage" * 10)
    with pytest.raises(ModelFileError, match=str(path.name)):
        load_model(path)
    # a pickle is refused, never executed
    torch.save(net.state_dict(), tmp_path / "p.safetensors")
    with pytest.raises(ModelFileError):
        load_model(tmp_path / "p.safetensors")
    # weights of another architecture
    save_model(tmp_path / "w", DefectNet(64, width=2), {"architecture": {"width": 1}})
    with pytest.raises(ModelFileError, match="incompatible"):
        load_model(tmp_path / "w")


def test_train_few_steps_resume_and_screen(tmp_path: Path) -> None:
    ds = write_dataset(tmp_path / "ds", n_per_class=20)
    cfg = ClassifierConfig(
        input_size_px=48, epochs=2, batch_size=16, learning_rate=1e-3, num_threads=1
    )
    t0 = time.perf_counter()
    meta = train(ds, tmp_path / "model", cfg, progress=False)
    assert time.perf_counter() - t0 < 60
    assert (tmp_path / "model" / "model.safetensors").is_file()
    assert (tmp_path / "model" / "checkpoint.pt").is_file()
    assert len(meta["history"]) == 2
    assert meta["training_data"]["n_val"] == 8  # 20% of the 40 frames
    # temperature scaling on the validation split, stored with the weights
    cal = meta["calibration"]
    assert cal["n_val"] == 8 and cal["after"]["nll"] <= cal["before"]["nll"] + 1e-9
    assert load_model(tmp_path / "model")[0].temperature == pytest.approx(cal["temperature"])
    # resume: a longer run continues from the checkpoint instead of starting again
    cfg3 = ClassifierConfig(
        input_size_px=48, epochs=3, batch_size=16, learning_rate=1e-3, num_threads=1
    )
    meta3 = train(ds, tmp_path / "model", cfg3, progress=False)
    assert [h["epoch"] for h in meta3["history"]] == [1, 2, 3]
    # NaN-safe comparison (an untrained net may call nothing "defect": precision NaN)
    assert json.dumps(meta3["history"][:2]) == json.dumps(meta["history"])

    # screening: batched p_defect per frame through the same preprocessing
    rng = np.random.default_rng(9)
    (tmp_path / "drive" / "frames").mkdir(parents=True)
    frames = []
    for i in range(5):
        p = tmp_path / "drive" / "frames" / f"{i:04d}.png"
        cv2.imwrite(str(p), cv2.cvtColor(road_image(rng, i % 2 == 1, 120), cv2.COLOR_GRAY2BGR))
        frames.append(Frame(i, p.name, p, i * 0.1))
    cam = Camera(120, 120, 100.0, 100.0, 60.0, 60.0, 1.0, 10.0)
    drive = Drive(tmp_path / "drive", cam, frames, None, None)
    before = torch.get_num_threads()
    probs = screen_drive(tmp_path / "model", drive, ClassifierConfig(screen_batch_size=2))
    assert sorted(probs) == [f.filename for f in frames]
    assert all(0.0 <= p <= 1.0 for p in probs.values())
    # the same probabilities on one thread; screening leaves torch's thread count as it was
    one = screen_drive(
        tmp_path / "model", drive, ClassifierConfig(screen_batch_size=2, screen_num_threads=1)
    )
    assert one == pytest.approx(probs, abs=1e-5) and torch.get_num_threads() == before
    cores = len(os.sched_getaffinity(0))
    assert screen_threads(ClassifierConfig(screen_num_threads=64)) == min(64, cores)
    # an unreadable frame in the middle is left out; the others keep their own p (frames are
    # decoded ahead of the net by worker threads: order and batching must not mix them up)
    bad = tmp_path / "drive" / "frames" / "bad.png"
    bad.write_bytes(b"not a png")
    frames_bad = [*frames[:2], Frame(9, bad.name, bad, 0.25), *frames[2:]]
    with_bad = screen_drive(
        tmp_path / "model",
        Drive(tmp_path / "drive", cam, frames_bad, None, None),
        ClassifierConfig(screen_batch_size=2),
    )
    assert with_bad == pytest.approx(probs, abs=1e-6) and bad.name not in with_bad
    assert screen_threads(ClassifierConfig(screen_num_threads=0, num_threads=3)) == 3

    # in a worker process, as a fused run screens: the same probabilities, and the worker's
    # errors come back as the same exception class, naming the file
    scfg = ClassifierConfig(screen_batch_size=2)
    with ScreeningJob(tmp_path / "model", scfg, progress=False) as job:
        job.send(frames_bad)
        assert job.result() == pytest.approx(with_bad, abs=1e-6)
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(b"\x00garbage" * 10)
    with ScreeningJob(corrupt, scfg, progress=False) as job:
        job.send(frames)
        with pytest.raises(ModelFileError, match="corrupt.safetensors"):
            job.result()
    # the camera's image mask: what lies under it never reaches the network, in this process
    # and in the worker (a bonnet painted differently in every frame screens the same)
    usable = np.ones((120, 120), bool)
    usable[90:] = False
    mcam = dataclasses.replace(cam, mask=ImageMask(usable, "mask.png"))
    painted = []
    for i, fr in enumerate(frames):
        img = cv2.imread(str(fr.path))
        img[90:] = (0, 60 * i, 255 - 40 * i)
        q = tmp_path / "drive" / "frames" / f"painted_{fr.filename}"
        cv2.imwrite(str(q), img)
        painted.append(Frame(fr.index, q.name, q, fr.timestamp_s))
    masked = screen_drive(tmp_path / "model", Drive(tmp_path / "drive", mcam, frames, None, None),
                          scfg)  # fmt: skip
    masked_painted = screen_drive(
        tmp_path / "model", Drive(tmp_path / "drive", mcam, painted, None, None), scfg
    )
    assert list(masked_painted.values()) == pytest.approx(list(masked.values()), abs=1e-6)
    unmasked_painted = screen_drive(
        tmp_path / "model", Drive(tmp_path / "drive", cam, painted, None, None), scfg
    )
    assert list(unmasked_painted.values()) != pytest.approx(list(probs.values()), abs=1e-6)
    with ScreeningJob(tmp_path / "model", scfg, progress=False) as job:
        job.send(painted, mcam.mask)
        assert list(job.result().values()) == pytest.approx(list(masked.values()), abs=1e-6)
    # a job that never got its frames (the drive failed to load) is killed on close: a failed
    # or interrupted run leaves no worker behind
    job = ScreeningJob(tmp_path / "model", scfg, progress=False)
    proc = job._proc
    job.close()
    assert proc is not None and proc.poll() is not None
    with pytest.raises(RoadsurfError, match="closed"):
        job.result()


def test_metrics_counts() -> None:
    m = metrics(np.array([1, 1, 0, 0, 0]), np.array([1, 0, 1, 0, 0]))
    assert (m["tp"], m["fn"], m["fp"], m["tn"]) == (1, 1, 1, 2)
    assert m["accuracy"] == pytest.approx(0.6)
    assert m["precision"] == pytest.approx(0.5) and m["recall"] == pytest.approx(0.5)


def test_train_command_and_model_error_exit(tmp_path: Path) -> None:
    """`roadsurf train` wiring; a bad model path exits with a clear message, not a traceback."""
    from typer.testing import CliRunner

    from roadsurf.cli import app

    ds = write_dataset(tmp_path / "ds", n_per_class=10)
    runner = CliRunner()
    res = runner.invoke(
        app, ["train", str(ds), "--out", str(tmp_path / "m"), "--epochs", "1", "--input-size", "48"]
    )
    assert res.exit_code == 0, res.output
    assert "model.safetensors" in res.output
    _, meta = load_model(tmp_path / "m")
    assert meta["input_size_px"] == 48 and meta["config"]["epochs"] == 1
    with pytest.raises(ModelFileError):
        screen_drive(tmp_path / "missing", tmp_path / "ds")


@pytest.mark.parametrize(("side", "frac"), [(48, 0.12), (64, 0.4), (32, 1.0)])
def test_highpass_blur_is_the_reflect_padded_separable_gaussian(side: int, frac: float) -> None:
    """The blur as two matrix products equals the plain definition: a normalised Gaussian of
    σ = frac · side, radius min(⌈3σ⌉, side - 1), convolved along rows then columns of the
    reflect-padded image (with σ = side the radius is clamped)."""
    import math

    import torch.nn.functional as F

    net = DefectNet(side, highpass_frac=frac)
    sigma = frac * side
    r = min(int(math.ceil(3 * sigma)), side - 1)
    g = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64) / sigma) ** 2)
    k = (g / g.sum()).view(1, 1, 1, -1)
    x = torch.from_numpy(np.random.default_rng(4).random((3, 1, side, side)))
    ref = F.conv2d(F.pad(x, (r, r, 0, 0), mode="reflect"), k)
    ref = F.conv2d(F.pad(ref, (0, 0, r, r), mode="reflect"), k.transpose(-1, -2))
    got = net.blur(x.float()).double()
    assert got.shape == x.shape
    assert float((got - ref).abs().max()) < 1e-5


def test_highpass_input_ignores_smooth_illumination_and_round_trips(tmp_path: Path) -> None:
    """highpass_frac > 0: a smooth illumination ramp barely changes the logits; the setting
    travels in the model metadata (it is not a weight)."""
    torch.manual_seed(1)
    net = DefectNet(64, highpass_frac=0.15).eval()
    rng = np.random.default_rng(2)
    tex = rng.normal(120, 20, (64, 64))
    ramp = np.linspace(-40, 40, 64)[None, :] * np.ones((64, 1))
    x0 = torch.from_numpy(np.clip(tex, 0, 255).astype(np.uint8))[None, None]
    x1 = torch.from_numpy(np.clip(tex + ramp, 0, 255).astype(np.uint8))[None, None]
    plain = DefectNet(64).eval()
    plain.load_state_dict(net.state_dict())
    with torch.no_grad():
        d_hp = float((net(x0) - net(x1)).abs().max())
        d_plain = float((plain(x0) - plain(x1)).abs().max())
    assert d_hp < 0.5 * d_plain
    save_model(
        tmp_path / "m", net, {"architecture": {"dropout": 0.5, "width": 1, "highpass_frac": 0.15}}
    )
    net2, _ = load_model(tmp_path / "m")
    assert net2.highpass_frac == 0.15 and torch.equal(net(x1), net2(x1))
    with pytest.raises(RoadsurfError):
        DefectNet(64, highpass_frac=2.0)
