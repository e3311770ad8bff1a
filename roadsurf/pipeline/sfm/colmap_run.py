"""The COLMAP half of the SfM baseline: run (or resume) pycolmap, and say why frames are missing.

All in ``OUT/colmap/``, resumable: each step (SIFT feature extraction with the intrinsics of
camera.yaml, sequential matching, incremental mapping with the intrinsics held fixed) is recorded
in ``OUT/colmap/state.json`` with a fingerprint of its settings and skipped when done. Every
model the mapper makes is kept in ``OUT/colmap/sparse/<k>/``.
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from roadsurf.core.atomic import atomic_path, read_json, write_json_atomic
from roadsurf.core.camera import Camera
from roadsurf.core.fingerprint import Fingerprint
from roadsurf.io import drivefolder as df
from roadsurf.io.drive import Drive
from roadsurf.pipeline.sfm.config import SfmBaselineConfig

if TYPE_CHECKING:
    import pycolmap

log = logging.getLogger(__name__)

# The pipeline's own names inside OUT (the rest of OUT follows roadsurf.io.runfolder)
COLMAP_DIR = "colmap"  # everything COLMAP writes, resumable
COLMAP_DATABASE = "database.db"  # features, matches, two-view geometries
COLMAP_SPARSE = "sparse"  # one sub-folder per model the mapper made
COLMAP_STATE = "state.json"  # finished steps with the fingerprint of their settings
COLMAP_MASK_PNG = "camera_mask.png"  # camera.yaml's mask for COLMAP's reader (0 = ignore)
DRIVE_FRAMES_DIR = df.FRAMES_DIR  # the drive's image folder, COLMAP's image_path


def colmap_camera(cam: Camera) -> tuple[str, str]:
    """camera.yaml -> (COLMAP model name, params string). COLMAP puts the pixel origin at the
    top-left *corner* of the first pixel; ours is at its centre, hence +0.5 on cx, cy."""
    cx, cy = cam.cx + 0.5, cam.cy + 0.5
    k1, k2, p1, p2, k3 = cam.dist
    if not cam.has_distortion:
        return "PINHOLE", f"{cam.fx},{cam.fy},{cx},{cy}"
    if k3 == 0.0:
        return "OPENCV", f"{cam.fx},{cam.fy},{cx},{cy},{k1},{k2},{p1},{p2}"
    return "FULL_OPENCV", f"{cam.fx},{cam.fy},{cx},{cy},{k1},{k2},{p1},{p2},{k3},0,0,0"


class _State:
    """OUT/colmap/state.json: which COLMAP steps finished, with the settings they used."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data: dict[str, str] = read_json(path) if path.is_file() else {}

    def done(self, step: str, fp: str) -> bool:
        return self.data.get(step) == fp

    def mark(self, step: str, fp: str) -> None:
        self.data[step] = fp
        write_json_atomic(self.path, self.data)

    def invalidate_from(self, steps: list[str]) -> None:
        for s in steps:
            self.data.pop(s, None)
        write_json_atomic(self.path, self.data)


def run_colmap(
    cfg: SfmBaselineConfig, drive: Drive, colmap_dir: Path, overwrite: bool
) -> tuple[dict[int, pycolmap.Reconstruction], dict[str, float]]:
    """Run (or resume) extraction, matching and mapping. Returns ({model index: Reconstruction},
    timings in seconds)."""
    import pycolmap

    if overwrite and colmap_dir.exists():
        shutil.rmtree(colmap_dir)
    colmap_dir.mkdir(parents=True, exist_ok=True)
    # COLMAP's own (glog) output: as configured, or everything with `roadsurf -v`.
    verbose = log.isEnabledFor(logging.DEBUG)
    pycolmap.logging.minloglevel = 0 if verbose else int(cfg.colmap_log_level)
    db_path = colmap_dir / COLMAP_DATABASE
    sparse_dir = colmap_dir / COLMAP_SPARSE
    state = _State(colmap_dir / COLMAP_STATE)
    names = [f.filename for f in drive.frames]
    image_dir = drive.root / DRIVE_FRAMES_DIR
    model, params = colmap_camera(drive.camera)
    timings: dict[str, float] = {}
    steps = ["features", "matches", "mapping"]

    # Image identity (size, mtime) is part of the fingerprint: a re-rendered or edited drive
    # with the same filenames must not reuse stale features.
    stats = [(f.path.stat().st_size, f.path.stat().st_mtime_ns) for f in drive.frames]
    # each step's fingerprint: its settings (and the previous step's) as sorted JSON, sha256
    feat_settings = [
        names,
        stats,
        model,
        params,
        cfg.max_num_features,
        cfg.max_image_size,
        pycolmap.__version__,
    ]
    mask = drive.camera.mask
    if mask is not None:  # the same pixels left out as in roadsurf run (0 = ignore)
        feat_settings.append(mask.digest)
    fp_feat = Fingerprint().add_json(feat_settings).hexdigest(16)
    if not state.done("features", fp_feat):
        state.invalidate_from(steps)
        if db_path.exists():
            db_path.unlink()  # a half-written database from a killed run is not trusted
        log.info("COLMAP: extracting SIFT features from %d images", len(names))
        t = time.perf_counter()
        reader = pycolmap.ImageReaderOptions(camera_model=model, camera_params=params)
        if mask is not None:
            mask_png = colmap_dir / COLMAP_MASK_PNG
            with atomic_path(mask_png) as tmp:
                cv2.imwrite(str(tmp), np.where(mask.usable, 255, 0).astype(np.uint8))
            reader.camera_mask_path = str(mask_png)
        ext = pycolmap.FeatureExtractionOptions()
        ext.sift.max_num_features = cfg.max_num_features
        ext.max_image_size = cfg.max_image_size
        ext.num_threads = cfg.num_threads
        pycolmap.extract_features(
            db_path,
            image_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=ext,
            device=pycolmap.Device.cpu,
        )
        timings["features_s"] = time.perf_counter() - t
        state.mark("features", fp_feat)
    else:
        log.info("COLMAP: features already extracted (resume)")

    match_settings = [fp_feat, cfg.overlap, cfg.min_num_inliers, cfg.seed]
    fp_match = Fingerprint().add_json(match_settings).hexdigest(16)
    if not state.done("matches", fp_match):
        state.invalidate_from(steps[1:])
        with pycolmap.Database.open(db_path) as db:  # drop partial matches of a killed run
            db.clear_matches()
            db.clear_two_view_geometries()
        log.info("COLMAP: sequential matching (overlap %d)", cfg.overlap)
        t = time.perf_counter()
        mo = pycolmap.FeatureMatchingOptions()
        mo.num_threads = cfg.num_threads
        po = pycolmap.SequentialPairingOptions(overlap=cfg.overlap, quadratic_overlap=False)
        vo = pycolmap.TwoViewGeometryOptions()
        vo.min_num_inliers = cfg.min_num_inliers
        vo.ransac.random_seed = cfg.seed
        pycolmap.match_sequential(
            db_path,
            matching_options=mo,
            pairing_options=po,
            verification_options=vo,
            device=pycolmap.Device.cpu,
        )
        timings["matching_s"] = time.perf_counter() - t
        state.mark("matches", fp_match)
    else:
        log.info("COLMAP: matches already computed (resume)")

    map_settings = [fp_match, cfg.min_num_matches, cfg.init_min_tri_angle_deg, cfg.seed]
    fp_map = Fingerprint().add_json(map_settings).hexdigest(16)
    if not state.done("mapping", fp_map) or not sparse_dir.is_dir():
        state.invalidate_from(steps[2:])
        tmp = colmap_dir / f"{COLMAP_SPARSE}.tmp"
        for p in (tmp, sparse_dir):
            if p.exists():
                shutil.rmtree(p)
        tmp.mkdir()
        log.info("COLMAP: incremental mapping")
        t = time.perf_counter()
        opts = pycolmap.IncrementalPipelineOptions()
        # Intrinsics come from camera.yaml: hold them fixed.
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
        opts.min_num_matches = cfg.min_num_matches
        opts.mapper.init_min_tri_angle = cfg.init_min_tri_angle_deg
        opts.num_threads = cfg.num_threads
        opts.random_seed = cfg.seed
        opts.min_model_size = 3
        pycolmap.set_random_seed(cfg.seed)
        from tqdm import tqdm

        with tqdm(total=len(names), desc="COLMAP mapping", unit="img", leave=False) as bar:
            pycolmap.incremental_mapping(
                db_path, image_dir, tmp, opts, next_image_callback=lambda: bar.update(1)
            )
        tmp.rename(sparse_dir)  # atomic: a killed mapping leaves no sparse/ to trust
        timings["mapping_s"] = time.perf_counter() - t
        state.mark("mapping", fp_map)
    else:
        log.info("COLMAP: sparse models already exist (resume)")

    models: dict[int, pycolmap.Reconstruction] = {}
    for sub in sorted(sparse_dir.iterdir()) if sparse_dir.is_dir() else []:
        if sub.is_dir() and sub.name.isdigit():
            models[int(sub.name)] = pycolmap.Reconstruction(sub)
    return models, timings


def not_registered_reasons(
    db_path: Path,
    missing: list[str],
    models: dict[int, pycolmap.Reconstruction],
    model_notes: dict[int, str],
    cfg: SfmBaselineConfig,
) -> dict[str, str]:
    """A reason for every valid frame in ``missing`` (not in the outputs). ``model_notes`` says
    why a model's images were not used (e.g. it could not be aligned to GPS)."""
    import pycolmap

    if not missing:
        return {}
    in_model: dict[str, list[int]] = {}
    for k, rec in models.items():
        for im in rec.images.values():
            if im.has_pose:
                in_model.setdefault(im.name, []).append(k)
    with pycolmap.Database.open(db_path) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        id2name = {v: k for k, v in ids.items()}
        best: dict[str, tuple[int, str]] = {}
        pair_ids, tvgs = db.read_two_view_geometries()
        for pid, g in zip(pair_ids, tvgs, strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            n_in = len(g.inlier_matches)
            for x, y in ((a, b), (b, a)):
                nx = id2name.get(x)
                if nx is not None and n_in > best.get(nx, (-1, ""))[0]:
                    best[nx] = (n_in, id2name.get(y, "?"))
        n_kp = {n: db.num_keypoints_for_image(i) for n, i in ids.items()}
    reasons: dict[str, str] = {}
    for n in missing:
        if n not in ids:
            reasons[n] = "not imported into the COLMAP database (unreadable by COLMAP)"
        elif n_kp.get(n, 0) < cfg.min_num_inliers:
            reasons[n] = f"only {n_kp.get(n, 0)} SIFT features (textureless, blurred or dark?)"
        elif n in in_model:
            k = in_model[n][0]
            size = models[k].num_reg_images()
            note = model_notes.get(k, "it was not used")
            reasons[n] = f"registered only in a second model (sparse/{k}, {size} images); {note}"
        elif best.get(n, (0, ""))[0] < cfg.min_num_matches:
            m, other = best.get(n, (0, ""))
            reasons[n] = (
                f"no verified two-view geometry with its {cfg.overlap} neighbours (best: "
                f"{m} inlier matches{' with ' + other if other else ''}); not in any model"
            )
        else:
            m, other = best[n]
            reasons[n] = (
                f"has {m} verified matches (with {other}) but the mapper could not register it "
                f"(absolute pose failed or too few triangulated points); not in any model"
            )
    return reasons


def software_versions() -> dict[str, str]:
    """Versions for report.json. roadsurf's comes from the installed package metadata: the
    pipeline layer may not import the top-level ``roadsurf`` module (tests/test_architecture.py)."""
    import platform
    from importlib.metadata import version

    import pycolmap

    rv = version("roadsurf")
    return {
        "roadsurf": rv,
        "pycolmap": pycolmap.__version__,
        "colmap": str(getattr(pycolmap, "COLMAP_version", "")),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }
