"""The dataset folder: its images, its labels.csv and their reading back.

``label_run`` labels the frames of one drive from its finished run folder (the rule is
``selflabel``) and writes their thumbnails; ``write_dataset`` augments the defect images and
writes the tables. The job that runs the physics pipeline on each drive and calls both is
``roadsurf.pipeline.label.label_drives``.

Dataset folder::

    DATASET/
      labels.csv     # one row per image: image,label,class,group,drive,frame,run,max_depth_m,
                     #   extent_cm2,n_deep,physics_label,rule,augmentation,source_image,
                     #   bbox_x0,bbox_y0,bbox_x1,bbox_y1 (defect box in image px, empty if none)
      balance.json   # class counts before/after augmentation, dropped frames by reason
      dataset.json   # config, drives and run folders used (provenance)
      images/<drive>/<frame>.png         # greyscale, store_size_px square (whole frame)
      images/<drive>/aug/<frame>__<aug>.png
"""

from __future__ import annotations

import csv
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from roadsurf.core.atomic import atomic_path, write_json_atomic, write_text_atomic
from roadsurf.core.config import to_dict
from roadsurf.core.errors import RoadsurfError
from roadsurf.core.imagemask import ImageMask
from roadsurf.detection.classifier import augment
from roadsurf.detection.classifier.config import CLASS_NAMES, ClassifierConfig
from roadsurf.detection.classifier.selflabel import (
    frame_figures,
    label_frame,
    read_defect_types,
    read_physics_labels,
    skip_for_cnn,
)
from roadsurf.io.drive import load_drive, read_image
from roadsurf.io.drive.staticpx import static_pixels_of_drive

log = logging.getLogger(__name__)


LABEL_FIELDS = [
    "image",
    "label",
    "class",
    "group",
    "drive",
    "frame",
    "run",
    "max_depth_m",
    "extent_cm2",
    "n_deep",
    "physics_label",
    "rule",
    "augmentation",
    "source_image",
    "bbox_x0",
    "bbox_y0",
    "bbox_x1",
    "bbox_y1",
]


# ---------------------------------------------------------------- image preprocessing (shared)
def thumbnail(image: np.ndarray, store_size_px: int, mask: ImageMask | None = None) -> np.ndarray:
    """Whole frame (H, W) grey or (H, W, 3) RGB uint8 -> square grey uint8 (S, S).

    The same function prepares training images and screened frames, so both see identical input.
    With the camera's image ``mask`` the pixels that never show the road (a burned-in stamp, the
    bonnet) are set to the road's median grey first (``ImageMask.fill``): the network sees
    neither a stamp's changing text nor a dark bonnet it could take for a hole.
    """
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.ndim != 2:
        raise ValueError(f"thumbnail expects (H, W) or (H, W, 3), got {image.shape}")
    if mask is not None:
        image = mask.fill(image)
    return cv2.resize(image, (store_size_px, store_size_px), interpolation=cv2.INTER_AREA)


def to_input(thumb: np.ndarray, input_size_px: int) -> np.ndarray:
    """Thumbnail (S, S) -> network input side (input_size_px, input_size_px) uint8."""
    if thumb.shape[0] == input_size_px and thumb.shape[1] == input_size_px:
        return thumb
    return cv2.resize(thumb, (input_size_px, input_size_px), interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------- dataset writing
def drive_key(i: int, drive_dir: Path) -> str:
    """The name of drive ``i`` in the dataset (its images folder, the groups)."""
    return f"{i:02d}_{drive_dir.resolve().name}"


def write_png(path: Path, img: np.ndarray) -> None:
    """Write a PNG atomically, making its folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise RoadsurfError(f"{path}: could not write PNG")


@dataclass
class RunLabels:
    """The labelled frames of one drive (rows of labels.csv, thumbnails written)."""

    rows: list[dict[str, Any]]
    dropped: dict[str, int]  # frames left out, by reason
    provenance: dict[str, Any]  # the drive's entry in dataset.json


def label_run(
    drive_dir: Path, run_dir: Path, key: str, out: Path, cfg: ClassifierConfig
) -> RunLabels:
    """Label every frame of the drive ``drive_dir`` from its finished run folder ``run_dir``
    and write the labelled thumbnails to ``out/images/<key>/``.

    Defect rows keep their thumbnail (``_thumb``) and defect box (``bbox``, thumbnail px) for
    the augmentation in ``write_dataset``.
    """
    rows: list[dict[str, Any]] = []
    dropped: dict[str, int] = {}
    drive = load_drive(drive_dir)
    static_pixels_of_drive(drive)  # a black border masked as the run masked it
    names = [f.filename for f in drive.frames]
    figs = frame_figures(run_dir, names, drive.camera.height_m, cfg)
    phys = read_physics_labels(run_dir)
    kinds = read_defect_types(run_dir)
    if phys is None:
        log.warning(
            "%s: no frames.csv (detection stage did not run); labels use depth+extent only",
            run_dir,
        )
    sx = cfg.store_size_px / drive.camera.width
    sy = cfg.store_size_px / drive.camera.height
    provenance = {
        "key": key,
        "drive": str(drive_dir.resolve()),
        "run": str(run_dir.resolve()),
        "camera_height_m": drive.camera.height_m,
        "Z_d_m": cfg.depth_threshold_m(drive.camera.height_m),
        "alpha": cfg.depth_threshold_m(drive.camera.height_m) / drive.camera.height_m,
        "physics_labels": phys is not None,
    }
    for fr in tqdm(drive.frames, desc=f"label {key}", unit="frame", leave=False):
        fig = figs.get(fr.filename)
        p = phys.get(fr.filename) if phys is not None else None
        label, rule = label_frame(fig, p, cfg)
        skipped = skip_for_cnn(label, kinds.get(fr.filename), cfg)
        if skipped is not None:
            label, rule = None, skipped
        if label is None:
            dropped[rule] = dropped.get(rule, 0) + 1
            continue
        try:
            thumb = thumbnail(read_image(fr), cfg.store_size_px, drive.camera.mask)
        except RoadsurfError as e:
            log.warning("%s: skipped (%s)", fr.path, e)
            dropped["unreadable"] = dropped.get("unreadable", 0) + 1
            continue
        rel = Path("images") / key / (Path(fr.filename).stem + ".png")
        write_png(out / rel, thumb)
        bbox = None
        if fig is not None and fig.bbox_px is not None and label == 1:
            b = fig.bbox_px
            bbox = (b[0] * sx, b[1] * sy, b[2] * sx, b[3] * sy)
        rows.append(
            {
                "image": rel.as_posix(),
                "label": label,
                "class": CLASS_NAMES[label],
                "group": f"{key}/{fr.filename}",
                "drive": str(drive_dir),
                "frame": fr.filename,
                "run": str(run_dir),
                "max_depth_m": f"{fig.max_depth_m:.4f}" if fig else "",
                "extent_cm2": f"{fig.extent_cm2:.1f}" if fig else "",
                "n_deep": fig.n_deep if fig else "",
                "physics_label": "" if p is None else int(p[0]),
                "rule": rule,
                "augmentation": "",
                "source_image": "",
                "bbox": bbox,
                "_thumb": thumb if label == 1 else None,
            }
        )
    return RunLabels(rows, dropped, provenance)


def write_dataset(
    out: Path,
    rows: list[dict[str, Any]],
    dropped: dict[str, int],
    provenance: list[dict[str, Any]],
    cfg: ClassifierConfig,
    started: float,
) -> dict[str, Any]:
    """Augment the defect rows (seeded by ``cfg.seed``), write labels.csv, balance.json and
    dataset.json (``started``: ``time.perf_counter()`` when labelling began). Returns the
    balance summary."""
    rng = np.random.default_rng(cfg.seed)
    before = {c: sum(1 for r in rows if r["label"] == k) for k, c in enumerate(CLASS_NAMES)}
    if cfg.augment:
        rows = rows + augment_rows(rows, out, cfg, rng)
    after = {c: sum(1 for r in rows if r["label"] == k) for k, c in enumerate(CLASS_NAMES)}
    write_labels(out / "labels.csv", rows)
    balance = {
        "before_augmentation": before,
        "after_augmentation": after,
        "defect_share_before": before["defect"] / max(1, sum(before.values())),
        "defect_share_after": after["defect"] / max(1, sum(after.values())),
        "dropped_frames": dropped,
        "training_also_uses": "balanced sampling" if cfg.balanced_sampling else "class weighting",
    }
    write_json_atomic(out / "balance.json", balance)
    write_json_atomic(
        out / "dataset.json",
        {
            "format": "roadsurf-defect-dataset",
            "version": 1,
            "class_names": list(CLASS_NAMES),
            "store_size_px": cfg.store_size_px,
            "drives": provenance,
            "config": to_dict(cfg),
            "labelling_rule": (
                "defect: physics frame label = 1 and >= min_defect_points points with d/h < -alpha "
                "over >= min_defect_area_cm2 (convex hull); non-defect: physics label = 0 and "
                "no such extent; disagreements dropped when drop_ambiguous"
            ),
            "elapsed_s": round(time.perf_counter() - started, 2),
        },
    )
    log.info(
        "dataset %s: before %s, after augmentation %s, dropped %s", out, before, after, dropped
    )
    return balance


def augment_rows(
    rows: list[dict[str, Any]], out: Path, cfg: ClassifierConfig, rng: np.random.Generator
) -> list[dict[str, Any]]:
    """Augmented copies of the defect rows (their PNGs written under ``out``) against class
    imbalance; each copy points back to its ``source_image``."""
    defects = [r for r in rows if r["label"] == 1]
    n_non = sum(1 for r in rows if r["label"] == 0)
    k = augment.copies_needed(len(defects), n_non, cfg.augment_target_ratio, cfg.augment_max_copies)
    new: list[dict[str, Any]] = []
    for r in defects:
        for name, img in augment.augment_image(r["_thumb"], r["bbox"], k, rng, cfg.rescale_range):
            src = Path(r["image"])
            rel = src.parent / "aug" / f"{src.stem}__{name.replace('+', '_')}.png"
            write_png(out / rel, img)
            new.append(
                {
                    **r,
                    "image": rel.as_posix(),
                    "augmentation": name,
                    "source_image": r["image"],
                    "bbox": None,
                    "_thumb": None,
                }
            )
    return new


def write_labels(path: Path, rows: list[dict[str, Any]]) -> None:
    """DATASET/labels.csv from the rows (``LABEL_FIELDS``; the bbox as four columns)."""
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=LABEL_FIELDS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        b = r.get("bbox")
        rec = {k: r.get(k, "") for k in LABEL_FIELDS if not k.startswith("bbox_")}
        for j, name in enumerate(("bbox_x0", "bbox_y0", "bbox_x1", "bbox_y1")):
            rec[name] = f"{b[j]:.1f}" if b else ""
        w.writerow(rec)
    write_text_atomic(path, buf.getvalue())


# ---------------------------------------------------------------- reading a dataset
@dataclass
class Dataset:
    """A loaded dataset: images (N, S, S) uint8 grey, labels (N,), groups (N,) and rows."""

    root: Path
    images: np.ndarray
    labels: np.ndarray
    groups: list[str]
    rows: list[dict[str, str]]
    meta: dict[str, Any]


def load_dataset(root: str | Path, input_size_px: int) -> Dataset:
    """Read DATASET/labels.csv and its PNGs, resized to the network input side."""
    from roadsurf.core.atomic import read_json

    root = Path(root)
    path = root / "labels.csv"
    if not path.is_file():
        raise RoadsurfError(
            f"{path}: not found; {root} is not a dataset folder. Make one with "
            "`roadsurf label DRIVE... --out DATASET`."
        )
    meta = read_json(root / "dataset.json") if (root / "dataset.json").is_file() else {}
    rows: list[dict[str, str]] = []
    imgs: list[np.ndarray] = []
    with open(path, newline="", encoding="utf-8") as f:
        for line, row in enumerate(csv.DictReader(f), start=2):
            try:
                lab = int(row["label"])
                img_path = root / row["image"]
            except (KeyError, ValueError) as e:
                raise RoadsurfError(f"{path} line {line}: bad row ({e}); expected label 0/1") from e
            img = cv2.imread(str(img_path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise RoadsurfError(f"{path} line {line}: cannot read image {img_path}")
            if lab not in (0, 1):
                raise RoadsurfError(f"{path} line {line}: label {lab} is not 0 or 1")
            imgs.append(to_input(img, input_size_px))
            rows.append(row)
    if not rows:
        raise RoadsurfError(f"{path}: the dataset has no images")
    return Dataset(
        root=root,
        images=np.stack(imgs),
        labels=np.array([int(r["label"]) for r in rows], dtype=np.int64),
        groups=[r.get("group") or r["image"] for r in rows],
        rows=rows,
        meta=meta,
    )
