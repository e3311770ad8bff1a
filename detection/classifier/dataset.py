"""Self-labelling (dissertation eq. 5.8-5.9) and the dataset folder.

For every drive the physics pipeline runs (or a finished run folder is reused). A frame's
reconstructed points are normalised by the camera height, X̄ = X / h; the frame is a *defect*
when points lie deeper than α = Z^d / h below the fitted road plane over a sufficient extent,
and the physics pipeline's own frame label (RUN/frames.csv, detection stage) agrees. Frames whose
3D evidence disagrees with the physics label are ambiguous and left out (``drop_ambiguous``), so
the CNN learns from clear cases only.

Dataset folder (written by ``label_drives``)::

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
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from roadsurf.core.atomic import atomic_path, write_json_atomic, write_text_atomic
from roadsurf.core.config import to_dict
from roadsurf.core.errors import RoadsurfError
from roadsurf.detection.classifier import augment
from roadsurf.detection.classifier.config import CLASS_NAMES, ClassifierConfig

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
def thumbnail(image: np.ndarray, store_size_px: int) -> np.ndarray:
    """Whole frame (H, W) grey or (H, W, 3) RGB uint8 -> square grey uint8 (S, S).

    The same function prepares training images and screened frames, so both see identical input.
    """
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.ndim != 2:
        raise ValueError(f"thumbnail expects (H, W) or (H, W, 3), got {image.shape}")
    return cv2.resize(image, (store_size_px, store_size_px), interpolation=cv2.INTER_AREA)


def to_input(thumb: np.ndarray, input_size_px: int) -> np.ndarray:
    """Thumbnail (S, S) -> network input side (input_size_px, input_size_px) uint8."""
    if thumb.shape[0] == input_size_px and thumb.shape[1] == input_size_px:
        return thumb
    return cv2.resize(thumb, (input_size_px, input_size_px), interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------- depth / extent per frame
@dataclass
class FrameFigures:
    """3D evidence for one frame, from the reconstructed pairs it belongs to."""

    max_depth_m: float  # deepest point below the road plane (m, positive down); 0 if none
    extent_cm2: float  # footprint of the points deeper than Z^d (convex hull, cm²)
    n_deep: int  # points deeper than Z^d
    n_points: int  # all reconstructed points in the frame
    bbox_px: tuple[float, float, float, float] | None  # deep points' box in the frame (px)


def _hull_area_m2(xy: np.ndarray) -> float:
    if xy.shape[0] < 3:
        return 0.0
    hull = cv2.convexHull(xy.astype(np.float32))
    return float(cv2.contourArea(hull))


def frame_figures(
    run_dir: Path, filenames: list[str], camera_height_m: float, cfg: ClassifierConfig
) -> dict[str, FrameFigures]:
    """Depth and extent of each frame from RUN/pairs/*.npz (eq. 5.8-5.9); see
    ``figures_from_pairs``. ``filenames`` are the drive's valid frames in capture order."""
    from roadsurf.reconstruction.types import load_pair, pair_filename

    pair_dir = Path(run_dir) / "pairs"
    pairs = []
    for i in range(len(filenames) - 1):
        p = pair_dir / pair_filename(i, i + 1)
        if not p.is_file():
            continue
        try:
            res = load_pair(p)
        except Exception as e:  # noqa: BLE001 - a damaged cache file only loses this pair
            log.warning("%s: cannot read pair (%s); frames %d-%d get no 3D label", p, e, i, i + 1)
            continue
        # the run folder's file name decides which frames the pair belongs to
        res.frame_a, res.frame_b = filenames[i], filenames[i + 1]
        pairs.append(res)
    return figures_from_pairs(pairs, camera_height_m, cfg)


def figures_from_pairs(
    pairs: Iterable[Any], camera_height_m: float, cfg: ClassifierConfig
) -> dict[str, FrameFigures]:
    """Depth and extent of each frame seen by ``pairs`` (PairResults) -> {filename: figures}.

    Points are normalised by the camera height, X̄ = X / h; a point is deep when its signed
    plane distance satisfies d / h < -α with α = Z^d / h. Frame a of a pair collects its pixels
    ``px_a``, frame b its ``px_b``. Frames with no successful pair are absent.
    """
    h = float(camera_height_m)
    alpha = cfg.depth_threshold_m(h) / h
    per_frame: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for res in pairs:
        if not res.ok or res.n_points == 0:
            continue
        d_bar = np.asarray(res.plane_dist_m, float) / h  # normalised depth, negative below road
        xy = np.asarray(res.points_cam_a_m, float)[:, :2]
        per_frame.setdefault(res.frame_a, []).append((d_bar, xy, np.asarray(res.px_a, float)))
        per_frame.setdefault(res.frame_b, []).append((d_bar, xy, np.asarray(res.px_b, float)))
    out: dict[str, FrameFigures] = {}
    for name, parts in per_frame.items():
        max_depth = 0.0
        extent = 0.0
        n_deep = 0
        n_pts = 0
        boxes = []
        for d_bar, xy, px in parts:
            n_pts += d_bar.size
            deep = d_bar < -alpha
            max_depth = max(max_depth, float(-d_bar.min() * h) if d_bar.size else 0.0)
            n_deep = max(n_deep, int(deep.sum()))
            extent = max(extent, _hull_area_m2(xy[deep]) * 1e4)
            if deep.any():
                q = px[deep]
                boxes.append((q[:, 0].min(), q[:, 1].min(), q[:, 0].max(), q[:, 1].max()))
        bbox = None
        if boxes:
            b = np.array(boxes)
            bbox = (
                float(b[:, 0].min()),
                float(b[:, 1].min()),
                float(b[:, 2].max()),
                float(b[:, 3].max()),
            )
        out[name] = FrameFigures(max(0.0, max_depth), extent, n_deep, n_pts, bbox)
    return out


def read_defect_types(run_dir: Path) -> dict[str, set[str]]:
    """RUN/defects.geojson -> {filename: types of the physics defects seen in that frame}
    (the features' ``frames`` property); {} when the file does not exist."""
    from roadsurf.io.formats import read_geojson

    path = Path(run_dir) / "defects.geojson"
    if not path.is_file():
        return {}
    out: dict[str, set[str]] = {}
    for k, feat in enumerate(read_geojson(path).get("features") or []):
        props = feat.get("properties") or {}
        frames, kind = props.get("frames", []), props.get("type")
        if not isinstance(frames, list) or not isinstance(kind, str):
            raise RoadsurfError(
                f"{path}: feature {k} has a 'frames' that is not a list or no 'type'; re-run "
                "the detection stage (`roadsurf run DRIVE --out RUN --overwrite`) to rewrite it"
            )
        for fn in frames:
            out.setdefault(str(fn), set()).add(kind)
    return out


def skip_for_cnn(label: int | None, types: set[str] | None, cfg: ClassifierConfig) -> str | None:
    """The drop rule when a defect frame's physics defects are all of ``cnn_skip_types``."""
    skip = set(cfg.cnn_skip_types)
    if label != 1 or not skip or not types or not types <= skip:
        return None
    return f"left_to_3d({','.join(sorted(types))})"


def read_physics_labels(run_dir: Path) -> dict[str, tuple[bool, str]] | None:
    """RUN/frames.csv -> {filename: (defect, source)}; None when the file does not exist."""
    path = Path(run_dir) / "frames.csv"
    if not path.is_file():
        return None
    out: dict[str, tuple[bool, str]] = {}
    with open(path, newline="", encoding="utf-8") as f:
        for line, row in enumerate(csv.DictReader(f), start=2):
            try:
                out[row["filename"]] = (
                    str(row["defect"]).strip().lower() in ("1", "true", "yes"),
                    (row.get("source") or "3d").strip(),
                )
            except KeyError as e:
                raise RoadsurfError(
                    f"{path} line {line}: missing column {e}; expected filename,defect,..."
                ) from e
    return out


def label_frame(
    fig: FrameFigures | None, physics: tuple[bool, str] | None, cfg: ClassifierConfig
) -> tuple[int | None, str]:
    """One frame's label (1 defect, 0 non-defect, None = not used) and the rule that decided."""
    if physics is not None and physics[1] == "cnn":
        return None, "no_3d(cnn_screened)"
    if fig is None:
        return None, "no_3d(pair_failed)"
    deep_enough = fig.n_deep >= cfg.min_defect_points and fig.extent_cm2 >= cfg.min_defect_area_cm2
    clear_road = fig.n_deep <= 1 or fig.extent_cm2 < 0.25 * cfg.min_defect_area_cm2
    if physics is None:
        if deep_enough:
            return 1, "depth+extent"
        if clear_road:
            return 0, "depth+extent"
        return (None, "ambiguous(depth)") if cfg.drop_ambiguous else (0, "depth+extent")
    phys = physics[0]
    if phys and deep_enough:
        return 1, "physics+depth+extent"
    if not phys and not deep_enough:
        if clear_road or not cfg.drop_ambiguous:
            return 0, "physics+depth+extent"
        return None, "ambiguous(some_depth)"
    if cfg.drop_ambiguous:
        return None, "ambiguous(physics_vs_depth)"
    return int(phys), "physics"


# ---------------------------------------------------------------- dataset writing
def _drive_key(i: int, drive_dir: Path) -> str:
    return f"{i:02d}_{drive_dir.resolve().name}"


def _write_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise RoadsurfError(f"{path}: could not write PNG")


def ensure_run(drive_dir: Path, run_dir: Path) -> Path:
    """Reuse a finished run folder, else run (or resume) the physics pipeline into it."""
    if (run_dir / "report.json").is_file() and (run_dir / "pairs").is_dir():
        log.info("reusing finished run %s for %s", run_dir, drive_dir)
        return run_dir
    from roadsurf.pipeline import run_drive

    log.info("running the physics pipeline on %s into %s", drive_dir, run_dir)
    run_drive(drive_dir, run_dir)
    return run_dir


def label_drives(
    drives: list[str | Path],
    out: str | Path,
    cfg: ClassifierConfig | None = None,
    *,
    runs: list[str | Path] | None = None,
    runs_dir: str | Path | None = None,
) -> dict[str, Any]:
    """Label every frame of ``drives`` with the physics pipeline and write the dataset ``out``.

    ``runs`` gives a finished run folder per drive (same order); otherwise each drive's run
    lives in ``runs_dir/<key>`` (default ``out/runs``) and is computed or resumed there.
    Returns the balance summary (also ``out/balance.json``).
    """
    from roadsurf.io.drive import load_drive, read_image

    cfg = cfg or ClassifierConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    drive_dirs = [Path(d) for d in drives]
    if runs is not None and len(runs) != len(drive_dirs):
        raise RoadsurfError(
            f"--run given {len(runs)} times for {len(drive_dirs)} drives; give one run folder "
            "per drive (in the same order) or none"
        )
    rdir = Path(runs_dir) if runs_dir is not None else out / "runs"
    rng = np.random.default_rng(cfg.seed)
    rows: list[dict[str, Any]] = []
    dropped: dict[str, int] = {}
    provenance = []
    t0 = time.perf_counter()
    for i, ddir in enumerate(drive_dirs):
        key = _drive_key(i, ddir)
        run_dir = Path(runs[i]) if runs is not None else ensure_run(ddir, rdir / key)
        if runs is not None and not (run_dir / "pairs").is_dir():
            raise RoadsurfError(
                f"{run_dir}: not a finished run folder (no pairs/); run `roadsurf run {ddir} "
                f"--out {run_dir}` first or leave out --run"
            )
        drive = load_drive(ddir)
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
        provenance.append(
            {
                "key": key,
                "drive": str(ddir.resolve()),
                "run": str(run_dir.resolve()),
                "camera_height_m": drive.camera.height_m,
                "Z_d_m": cfg.depth_threshold_m(drive.camera.height_m),
                "alpha": cfg.depth_threshold_m(drive.camera.height_m) / drive.camera.height_m,
                "physics_labels": phys is not None,
            }
        )
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
                thumb = thumbnail(read_image(fr), cfg.store_size_px)
            except RoadsurfError as e:
                log.warning("%s: skipped (%s)", fr.path, e)
                dropped["unreadable"] = dropped.get("unreadable", 0) + 1
                continue
            rel = Path("images") / key / (Path(fr.filename).stem + ".png")
            _write_png(out / rel, thumb)
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
                    "drive": str(ddir),
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
    before = {c: sum(1 for r in rows if r["label"] == k) for k, c in enumerate(CLASS_NAMES)}
    if cfg.augment:
        rows += _augment_rows(rows, out, cfg, rng)
    after = {c: sum(1 for r in rows if r["label"] == k) for k, c in enumerate(CLASS_NAMES)}
    _write_labels(out / "labels.csv", rows)
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
            "elapsed_s": round(time.perf_counter() - t0, 2),
        },
    )
    log.info(
        "dataset %s: before %s, after augmentation %s, dropped %s", out, before, after, dropped
    )
    return balance


def _augment_rows(
    rows: list[dict[str, Any]], out: Path, cfg: ClassifierConfig, rng: np.random.Generator
) -> list[dict[str, Any]]:
    defects = [r for r in rows if r["label"] == 1]
    n_non = sum(1 for r in rows if r["label"] == 0)
    k = augment.copies_needed(len(defects), n_non, cfg.augment_target_ratio, cfg.augment_max_copies)
    new: list[dict[str, Any]] = []
    for r in defects:
        for name, img in augment.augment_image(r["_thumb"], r["bbox"], k, rng, cfg.rescale_range):
            src = Path(r["image"])
            rel = src.parent / "aug" / f"{src.stem}__{name.replace('+', '_')}.png"
            _write_png(out / rel, img)
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


def _write_labels(path: Path, rows: list[dict[str, Any]]) -> None:
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
