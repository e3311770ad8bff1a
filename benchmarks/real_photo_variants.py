"""Benchmark: real photographs changed as other cameras and set-ups would change them.

roadsurf is measured on real photographs it never saw. This bench makes physically honest
variants of a real drive with pixel labels (by default spd2: ../shared/real/spd2, its README),
each a drive of its own with camera.yaml and the labels moved with the pixels, runs
``benchmarks.real_photos`` on each and tabulates frame recall, mask IoU, defects and depths
against the unchanged drive (``base``) run the same way in the same call.

    python -m benchmarks.real_photo_variants --cases base,frame20,barrel --work W
    make bench-real_photo_variants ARGS="--cases base,frame20,barrel"

Cases (``--cases``, default all):
- ``base``: the drive as it is, the same files (the control); every case that changes the
  pixels writes JPEG q92 again (re-encoding alone moves single depths by a few %);
- ``frame20``: a 20 px black frame round every image (a letterbox);
- ``barrel``: barrel distortion k1 = -0.1 applied and written to camera.yaml, with the black
  edges such a remap leaves (what undistorting in reverse would leave);
- ``crop``: the centre 1280 x 720 (principal point moved);
- ``half``: half resolution (intrinsics halved);
- ``q50``: JPEG quality 50;
- ``grey``: 8-bit greyscale PNG;
- ``expo``: alternate frames x0.6 and x1.4 brightness (auto-exposure), clipped;
- ``rot180``: the camera mounted upside down (images and principal point turned 180°);
- ``height10``: camera.yaml's height_m 10 % high (depths should read ~10 % deep).
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import yaml

from benchmarks._result import write_result
from benchmarks.real_photos import SPD2

ImageFn = Callable[[np.ndarray, int], np.ndarray]
LabelFn = Callable[[np.ndarray], np.ndarray]


def _frames(drive: Path) -> list[dict[str, str]]:
    with open(drive / "frames.csv", newline="") as f:
        return list(csv.DictReader(f))


def _make(
    src: Path,
    out: Path,
    cam_update: Callable[[dict], dict] | None = None,
    img_fn: ImageFn | None = None,
    lab_fn: LabelFn | None = None,
    ext: str | None = None,
    jpeg_q: int = 92,
) -> Path:
    """A copy of drive ``src`` (labels beside it) in ``out`` with the images, labels and
    camera.yaml changed; returns the new drive folder."""
    drive, labels = out / "drive", out / "labels"
    if out.exists():
        shutil.rmtree(out)
    (drive / "frames").mkdir(parents=True)
    labels.mkdir()
    cam = yaml.safe_load((src / "camera.yaml").read_text())
    if cam_update is not None:
        cam = cam_update(cam)
    (drive / "camera.yaml").write_text(yaml.safe_dump(cam, sort_keys=False))
    rows = []
    for i, r in enumerate(_frames(src)):
        stem = Path(r["filename"]).stem
        name = stem + (ext or Path(r["filename"]).suffix)
        if img_fn is None and ext is None:  # the same pixels: the same bytes (no re-encoding)
            shutil.copyfile(src / "frames" / r["filename"], drive / "frames" / name)
        else:
            img = cv2.imread(str(src / "frames" / r["filename"]), cv2.IMREAD_COLOR)
            if img is None:
                raise SystemExit(f"{src / 'frames' / r['filename']}: unreadable")
            if img_fn is not None:
                img = img_fn(img, i)
            params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_q] if name.endswith(".jpg") else []
            cv2.imwrite(str(drive / "frames" / name), img, params)
        lab = cv2.imread(str(src.parent / "labels" / f"{stem}.png"), cv2.IMREAD_GRAYSCALE)
        if lab is not None:
            cv2.imwrite(str(labels / f"{stem}.png"), lab_fn(lab) if lab_fn else lab)
        rows.append((name, r["timestamp_s"]))
    with open(drive / "frames.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["filename", "timestamp_s"])
        w.writerows(rows)
    return drive


def _border(img: np.ndarray, _i: int, px: int = 20) -> np.ndarray:
    out = img.copy()
    out[:px], out[-px:], out[:, :px], out[:, -px:] = 0, 0, 0, 0
    return out


def _barrel_maps(cam: dict, k1: float) -> tuple[np.ndarray, np.ndarray]:
    """Remap maps: for each pixel of the distorted image, where it lies in the pinhole one."""
    w, h = int(cam["width"]), int(cam["height"])
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], float)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6)
    und = cv2.undistortPoints(pts, K, np.array([k1, 0, 0, 0, 0.0]), P=K, criteria=crit)
    mx = und[:, 0, 0].reshape(h, w).astype(np.float32)
    my = und[:, 0, 1].reshape(h, w).astype(np.float32)
    return mx, my


def _case(name: str, src: Path, out: Path) -> Path:
    """Make case ``name`` of drive ``src`` in ``out``; returns the drive folder."""
    cam = yaml.safe_load((src / "camera.yaml").read_text())
    w, h = int(cam["width"]), int(cam["height"])
    if name == "base":
        return _make(src, out)
    if name == "frame20":
        return _make(src, out, img_fn=_border)
    if name == "barrel":
        mx, my = _barrel_maps(cam, -0.1)

        def remap(a: np.ndarray, interp: int) -> np.ndarray:
            return cv2.remap(a, mx, my, interp, borderMode=cv2.BORDER_CONSTANT)

        return _make(
            src, out, lambda c: {**c, "dist": [-0.1, 0.0, 0.0, 0.0, 0.0]},
            lambda im, i: remap(im, cv2.INTER_LINEAR), lambda lab: remap(lab, cv2.INTER_NEAREST),
        )  # fmt: skip
    if name == "crop":
        cw, ch = min(1280, w), min(720, h)
        x0, y0 = (w - cw) // 2, (h - ch) // 2

        def cut(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(a[y0 : y0 + ch, x0 : x0 + cw])

        return _make(
            src, out,
            lambda c: {**c, "width": cw, "height": ch, "cx": c["cx"] - x0, "cy": c["cy"] - y0},
            lambda im, i: cut(im), cut,
        )  # fmt: skip
    if name == "half":
        size = (w // 2, h // 2)

        def halve(c: dict) -> dict:
            return {
                **c, "width": size[0], "height": size[1], "fx": c["fx"] / 2, "fy": c["fy"] / 2,
                "cx": (c["cx"] + 0.5) / 2 - 0.5, "cy": (c["cy"] + 0.5) / 2 - 0.5,
            }  # fmt: skip

        return _make(
            src, out, halve, lambda im, i: cv2.resize(im, size, interpolation=cv2.INTER_AREA),
            lambda lab: cv2.resize(lab, size, interpolation=cv2.INTER_NEAREST),
        )  # fmt: skip
    if name == "q50":
        return _make(src, out, ext=".jpg", jpeg_q=50)
    if name == "grey":
        return _make(
            src, out, img_fn=lambda im, i: cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), ext=".png"
        )
    if name == "expo":

        def gain(im: np.ndarray, i: int) -> np.ndarray:
            g = 0.6 if i % 2 == 0 else 1.4
            return np.clip(im.astype(np.float32) * g + 0.5, 0, 255).astype(np.uint8)

        return _make(src, out, img_fn=gain)
    if name == "rot180":
        return _make(
            src, out, lambda c: {**c, "cx": w - 1 - c["cx"], "cy": h - 1 - c["cy"]},
            lambda im, i: cv2.rotate(im, cv2.ROTATE_180), lambda lab: cv2.rotate(lab, cv2.ROTATE_180),
        )  # fmt: skip
    if name == "height10":
        return _make(src, out, lambda c: {**c, "height_m": float(c["height_m"]) * 1.1})
    raise SystemExit(f"--cases: unknown case {name!r}; see the module's docstring")


CASES = ("base", "frame20", "barrel", "crop", "half", "q50", "grey", "expo", "rot180", "height10")
KEYS = ("frame_recall_ok_pairs", "frame_precision_ok_pairs", "mask_iou_median", "pairs_ok",
        "defects", "map_noise_mm", "depths_in_range")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--drive", type=Path, default=SPD2 / "drive", help="a real drive; labels/ beside it"
    )
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated (default: all)")
    ap.add_argument("--work", type=Path, default=Path("out/bench_real_photo_variants"))
    ap.add_argument("--depth-range-mm", default="24,39", help="expected depths (real_photos)")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    rows: dict[str, dict] = {}
    for name in a.cases.split(","):
        out = a.work / name
        drive = _case(name, a.drive, out)
        res = out / "result.json"
        cmd = [sys.executable, "-m", "benchmarks.real_photos", "--drive", str(drive),
               "--work", str(out / "bench"), "--depth-range-mm", a.depth_range_mm,
               "--json", str(res)]  # fmt: skip
        print(f"{name}: {' '.join(cmd)}", flush=True)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        fig = json.loads(res.read_text())["figures"]
        log = (out / "bench" / "run.log").read_text(errors="replace")
        rows[name] = {k: fig.get(k) for k in KEYS} | {
            "warnings": sum(" WARNING " in line for line in log.splitlines()),
            "black_border_masked": "black in every frame" in log,
        }
        print(name, rows[name], flush=True)
    head = "| case | recall | precision | IoU median | pairs ok | defects | noise (mm) | depths in range |"
    lines = [head, "|" + "---|" * 8]
    for name, r in rows.items():
        lines.append(
            f"| {name} | {r['frame_recall_ok_pairs']:.3f} | {r['frame_precision_ok_pairs']:.3f} | "
            f"{r['mask_iou_median']:.3f} | {r['pairs_ok']} | {r['defects']} | "
            f"{r['map_noise_mm']:.3f} | {r['depths_in_range']} |"
        )
    md = "\n".join(lines)
    print(md)
    write_result(
        a.json, "real_photo_variants", {"drive": str(a.drive), "cases": rows, "table_markdown": md}
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
