"""`roadsurf run`: chain the stages over one drive. No stage logic lives here.

Order: load_drive -> [CNN screening, decides which pairs are reconstructed] ->
reconstruction.stage.run -> mapping.poses.run -> mapping.globalmap.run -> detection.stage.run
-> report.json. Each stage resumes from its own artifacts in the run folder.

Stages are imported lazily inside ``_run_drive`` (keeps `roadsurf --help` fast) but called
explicitly. Live streaming is an observer that the CLI passes in (``roadsurf.viewer.live``): the
pipeline never imports the viewer. An observer is any callable ``observer(stage_name, result)``
called after each stage with that stage's result (``"drive"``: Drive, ``"screening"``: dict filename -> p,
``"reconstruction"``: list[PairResult], ``"poses"``: Trajectory, ``"globalmap"``: MapProducts,
``"detection"``: DetectionResult).
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from roadsurf.core.atomic import (
    output_error,
    read_json,
    remove_stale_temporaries,
    write_json_atomic,
)
from roadsurf.core.config import from_dict, load_yaml_config, to_dict
from roadsurf.core.errors import ConfigError
from roadsurf.core.memory import fix_mmap_threshold, limit_malloc_arenas, release_free_memory
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.config import DetectionConfig
from roadsurf.io import runfolder as rf
from roadsurf.io.formats import LOCAL_FRAME_TEXT
from roadsurf.mapping.bundle_camera import later_stage_inputs
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.datum import vertical_datum
from roadsurf.mapping.loops import frame_matcher
from roadsurf.pipeline.run_checks import (
    check_out_folder,
    check_reconstruction,
    claim_run_folder,
    static_pixels,
)
from roadsurf.pipeline.run_checks import pair_failures_warning as failures_warning
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.types import STATUS_NO_MOTION

if TYPE_CHECKING:
    from roadsurf.detection.classifier.fusion import FusionRule
    from roadsurf.detection.classifier.screen_job import ScreeningJob
    from roadsurf.detection.types import DetectionResult
    from roadsurf.io.drive import Drive
    from roadsurf.mapping.types import MapProducts, Trajectory
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)
T = TypeVar("T")

Observer = Callable[[str, Any], None]


@dataclass(frozen=True)
class PipelineConfig:
    """All stage configs; the YAML file's top-level keys are these field names."""

    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    detection: DetectionConfig = field(default_factory=DetectionConfig)
    classifier: ClassifierConfig = field(default_factory=ClassifierConfig)


def load_pipeline_config(path: str | Path | None) -> PipelineConfig:
    """Load a YAML config (top-level keys = stage names); defaults when ``path`` is None."""
    if path is None:
        return PipelineConfig()
    return load_yaml_config(PipelineConfig, path)


# What a fused run imports after screening: the stage modules and the heavy libraries they
# import inside functions. A stale entry only costs overlap, never correctness
_FUSED_RUN_IMPORTS = (
    "roadsurf.reconstruction.stage",
    "roadsurf.reconstruction.probe",
    "roadsurf.detection.classifier.guided",
    "roadsurf.mapping.poses",
    "roadsurf.mapping.globalmap",
    "roadsurf.detection.stage",
    "roadsurf.detection.cracks",
    "roadsurf.detection.dense",
    "roadsurf.detection.ruts",
    "rasterio",
    "rasterio.windows",
    "shapely",
    "matplotlib.tri",
    "matplotlib.path",
    "skimage.morphology",
    "scipy.sparse.csgraph",
    "scipy.spatial",
)


def _screen(
    model: Path, drive: Drive, cfg: ClassifierConfig, job: ScreeningJob | None
) -> dict[str, float]:
    """CNN screening of every frame -> {filename: p_defect}: by the worker process ``job``
    (``screen_job``, started with the run) while this process imports what the rest of the
    run needs (imports hold the GIL, so a thread could not overlap them), or in this process
    when ``job`` is None."""
    if job is None:
        from roadsurf.detection.classifier.screen import screen_drive

        return screen_drive(model, drive, cfg)
    job.send(drive.frames, drive.camera.mask)
    for name in _FUSED_RUN_IMPORTS:
        try:
            importlib.import_module(name)
        except ImportError as e:  # the stage that needs it reports it when it runs
            log.debug("warm-up import of %s failed: %s", name, e)
    return job.result()


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in (
        "roadsurf",
        "numpy",
        "scipy",
        "opencv-python-headless",
        "pycolmap",
        "open3d",
        "rasterio",
        "pyproj",
        "torch",
        "rerun-sdk",
    ):
        try:
            from importlib.metadata import version

            out[name] = version(name)
        except Exception:  # noqa: BLE001 - a missing optional package is just not listed
            continue
    return out


def run_drive(
    drive_dir: str | Path,
    out_dir: str | Path,
    *,
    config_path: str | Path | None = None,
    method: str | None = None,
    classifier: str | Path | None = None,
    overwrite: bool = False,
    observers: Sequence[Observer] | None = None,
) -> dict[str, Any]:
    """Run every stage on ``drive_dir`` into ``out_dir``; returns the report (also report.json).

    ``method`` picks the reconstruction estimator (None: the config's, by default the
    rotation-aware variant of the proposed method); ``classifier`` is a CNN model file for
    screening (only pairs the CNN is unsure about, or calls defect, are reconstructed);
    ``observers`` are called after each stage (the CLI's ``--rerun`` streams to Rerun through
    one); ``overwrite`` recomputes finished
    artifacts instead of resuming.
    """
    t_start = time.perf_counter()
    check_out_folder(Path(drive_dir), Path(out_dir))
    limit_malloc_arenas()  # before the stages' threads allocate (roadsurf.core.memory)
    cfg = load_pipeline_config(config_path)
    job = None
    if classifier is not None and cfg.classifier.screen_in_subprocess:
        # a fused run starts its CNN worker first: torch's import and the model's loading run
        # on another core while this process reads the drive and imports the stages
        from roadsurf.detection.classifier.screen_job import ScreeningJob

        job = ScreeningJob(Path(classifier), cfg.classifier)
    try:
        try:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise output_error(e, Path(out_dir)) from e
        with rf.run_folder_lock(out_dir):  # one run per folder (its temporaries are its own)
            return _run_drive(
                drive_dir, Path(out_dir), cfg, method, classifier, overwrite, observers, job,
                t_start,
            )  # fmt: skip
    finally:
        if job is not None:
            job.close()  # kills the worker if the run stopped before its result


def _run_drive(
    drive_dir: str | Path,
    out: Path,
    cfg: PipelineConfig,
    method: str | None,
    classifier: str | Path | None,
    overwrite: bool,
    observers: Sequence[Observer] | None,
    job: ScreeningJob | None,
    t_start: float,
) -> dict[str, Any]:
    """``run_drive`` with its config loaded and its screening worker (``job``, or None) started."""
    from roadsurf.detection import stage as detection_stage
    from roadsurf.io.drive import along_track_m, load_drive
    from roadsurf.mapping import globalmap, poses
    from roadsurf.reconstruction import stage as reconstruction_stage

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise output_error(e, out) from e
    for tmp in remove_stale_temporaries(out):
        log.info("removed a temporary file left by an interrupted run: %s", tmp)
    obs: list[Observer] = list(observers or [])
    timings: dict[str, float] = {}
    started: dict[str, float] = {}  # wall-clock start of each stage (artifact mtimes vs this)
    previous = _previous_stage_timings(out)

    def notify(stage: str, result: Any) -> None:
        for o in obs:
            try:
                o(stage, result)
            except Exception as e:  # noqa: BLE001 - a viewer problem must not kill the run
                log.warning("observer failed on stage %s: %s", stage, e)

    def timed(name: str, fn: Callable[[], T]) -> T:
        started[name] = time.time()
        t0 = time.perf_counter()
        res = fn()
        timings[name] = round(time.perf_counter() - t0, 3)
        log.info("stage %s done in %.1f s", name, timings[name])
        notify(name, res)
        release_free_memory()  # what the stage freed, so the next one starts low
        return res

    drive = timed("drive", lambda: load_drive(drive_dir))
    claim_run_folder(drive_dir, out, overwrite)  # refuses another drive's run folder
    static_pixels(drive, out)  # a warning in drive.warnings and RUN/suggested_mask.png

    if overwrite:
        cfg = _with_overwrite(cfg)
    rec_cfg = cfg.reconstruction
    if method is not None:
        if not any(f.name == "method" for f in dataclasses.fields(rec_cfg)):
            raise ConfigError(f"--method {method}: the reconstruction stage has no method option")
        rec_cfg = from_dict(type(rec_cfg), {**to_dict(rec_cfg), "method": method}, "--method")
    frame_probs: dict[str, float] | None = None
    fusion_rule: FusionRule | None = None
    if classifier is None:
        pairs = timed("reconstruction", lambda: reconstruction_stage.run(rec_cfg, drive, out))
    else:
        frame_probs = timed(
            "screening", lambda: _screen(Path(classifier), drive, cfg.classifier, job)
        )
        from roadsurf.detection.classifier import guided
        from roadsurf.reconstruction import probe

        def reconstruct_guided() -> list[PairResult]:
            nonlocal fusion_rule
            g = guided.run(
                cfg.classifier,
                [f.filename for f in drive.frames],
                frame_probs,
                drive.camera.height_m,
                lambda only: reconstruction_stage.run(rec_cfg, drive, out, only_pairs=only),
                out,
                along_m=along_track_m(drive),
                probe=lambda only: probe.run(rec_cfg, drive, out, only),
            )
            fusion_rule = g.rule
            return g.pairs

        pairs = timed("reconstruction", reconstruct_guided)
    check_reconstruction(pairs, drive, rec_cfg, out)
    # from here on, freed tile-sized arrays go back to the system, not into the arenas (not
    # during the reconstruction: its image-sized temporaries would each cost a map + page faults)
    fix_mmap_threshold()
    # revisits (issue 30): frames of two passes are matched with the pair API and close the loop
    loop_match = frame_matcher(drive, rec_cfg, out)
    traj = timed("poses", lambda: poses.run(cfg.mapping, drive, pairs, out, loop_match=loop_match))
    # the later stages see the camera on the mount the poses used (given or estimated) and with
    # the bundle's refined focal and k1, the pairs re-derived with them (issue 30)
    drive, pairs = later_stage_inputs(drive, pairs, traj, out, rec_cfg.plane_trim_k)
    products = timed("globalmap", lambda: globalmap.run(cfg.mapping, drive, pairs, traj, out))
    detections = timed(
        "detection",
        lambda: detection_stage.run(
            cfg.detection, drive, pairs, traj, out, frame_probs=frame_probs, fusion=fusion_rule
        ),
    )

    timings["total"] = round(time.perf_counter() - t_start, 3)
    stages = stage_timings(out, timings, started, previous, _own_timings(out, pairs))
    report = _build_report(
        drive,
        pairs,
        traj,
        products,
        detections,
        cfg,
        getattr(rec_cfg, "method", method),
        timings,
        out,
    )
    if classifier is not None and (out / rf.SCREENING_JSON).is_file():
        # CNN screening summary of this run (per-frame details stay in screening.json)
        scr = read_json(out / rf.SCREENING_JSON)
        report["screening"] = {"model": str(Path(classifier).resolve())} | {
            k: v for k, v in scr.items() if k != "frames"
        }
        report["warnings"] += list(scr.get("warnings") or [])
    report["stages"] = stages
    report["resumed_stages"] = [k for k, v in stages.items() if v["resumed"] != "no"]
    report["timings_this_run_s"] = timings
    # timings of the run that computed each stage (a resumed stage keeps its original time)
    report["timings_s"] = {
        **{k: v["computed_s"] for k, v in stages.items() if v["computed_s"] is not None},
        "total": round(sum(v["computed_s"] or 0.0 for v in stages.values()), 3),
    }
    write_json_atomic(out / rf.REPORT_JSON, report)
    notify("report", report)
    return report


# artifacts whose modification time tells whether a stage computed or resumed (run-folder paths)
STAGE_ARTIFACTS: dict[str, tuple[str, ...]] = {
    "reconstruction": (rf.PAIRS_DIR,),
    "poses": (rf.POSES_NPZ,),
    "globalmap": (rf.MAP_REPORT,),
    "detection": (rf.DEFECTS_GEOJSON,),
}


def _previous_stage_timings(out: Path) -> dict[str, Any]:
    """Per-stage timings recorded by an earlier run in ``out`` (report.json), if any."""
    try:
        rep = read_json(out / rf.REPORT_JSON)
    except (OSError, ValueError):
        return {}
    if not isinstance(rep, dict):
        return {}  # not a report (damaged): this run writes a new one
    stages = rep.get("stages")
    if isinstance(stages, dict):
        return stages
    # an older report without "stages": its timings_s are the times of that run
    t = rep.get("timings_s") or {}
    return {k: {"computed_s": v} for k, v in t.items() if k != "total"}


def _own_timings(out: Path, pairs: list[PairResult]) -> dict[str, float | None]:
    """Compute times the stages recorded in their own artifacts (for resumed stages)."""
    own: dict[str, float | None] = {}
    secs = [sum(getattr(p, "timings_s", {}).values()) for p in pairs]
    own["reconstruction"] = round(float(sum(secs)), 3) if any(secs) else None
    for name, file, key in (
        ("poses", rf.POSES_REPORT, ("elapsed_s",)),
        ("globalmap", rf.MAP_REPORT, ("timings_s", "total")),
    ):
        try:
            v: Any = read_json(out / file)
            for k in key:
                v = v.get(k) if isinstance(v, dict) else None
            own[name] = float(v) if isinstance(v, (int, float)) else None
        except (OSError, ValueError):
            own[name] = None
    return own


def _mtimes(path: Path) -> list[float]:
    if path.is_dir():
        return [f.stat().st_mtime for f in path.iterdir() if f.is_file()]
    return [path.stat().st_mtime] if path.exists() else []


def stage_timings(
    out: Path,
    this_run_s: dict[str, float],
    started: dict[str, float],
    previous: dict[str, Any],
    own: dict[str, float | None] | None = None,
) -> dict[str, dict[str, Any]]:
    """For each stage of this run: ``this_run_s`` (seconds spent now), ``resumed`` ("no",
    "all" when every artifact predates the stage's start, "partial" when some do, e.g. a
    killed reconstruction) and ``computed_s``: the time of the run(s) that computed it (this
    run's time, plus the earlier run's for a partial resume; None when unknown). For a
    resumed stage, ``computed_s`` comes from the earlier report's per-stage record, else from
    ``own`` (the time a stage recorded in its own artifacts), else from an older report."""
    out_s: dict[str, dict[str, Any]] = {}
    for name, secs in this_run_s.items():
        if name == "total":
            continue
        resumed = "no"
        arts = STAGE_ARTIFACTS.get(name, ())
        mt = [m for a in arts for m in _mtimes(out / a)]
        t0 = started.get(name)
        if mt and t0 is not None:
            old = [m < t0 - 1e-3 for m in mt]
            resumed = "all" if all(old) else ("partial" if any(old) else "no")
        prev = previous.get(name, {}) if isinstance(previous.get(name), dict) else {}
        prev_s = prev.get("computed_s")
        if resumed == "all":
            computed = prev_s if "resumed" in prev else None  # a per-stage record: trusted
            if computed is None:
                computed = (own or {}).get(name)
            if computed is None:
                computed = prev_s
        elif resumed == "partial":
            computed = round(secs + float(prev_s or 0.0), 3)
        else:
            computed = secs
        out_s[name] = {"computed_s": computed, "this_run_s": secs, "resumed": resumed}
    return out_s


def _with_overwrite(cfg: PipelineConfig) -> PipelineConfig:
    """Set ``overwrite=True`` in every stage config that has that field."""
    repl = {}
    for f in dataclasses.fields(cfg):
        sub = getattr(cfg, f.name)
        if any(g.name == "overwrite" for g in dataclasses.fields(sub)):
            repl[f.name] = dataclasses.replace(sub, overwrite=True)
    return dataclasses.replace(cfg, **repl)


def _build_report(
    drive: Drive,
    pairs: list[PairResult],
    traj: Trajectory | None,
    products: MapProducts | None,
    detections: DetectionResult | None,
    cfg: PipelineConfig,
    method: str | None,
    timings: dict[str, float],
    out: Path,
) -> dict[str, Any]:
    ef = traj.export_frame if traj is not None else None
    failed = [
        {"frame_a": p.frame_a, "frame_b": p.frame_b, "status": p.status, "reason": p.reason}
        for p in pairs
        if not p.ok
    ]
    report: dict[str, Any] = {
        "drive": str(Path(drive.root).resolve()),
        "method": method,
        "crs": ef.crs if ef is not None else None,
        # without GPS every output is in a local metric frame, never lon/lat
        "coordinates": (
            f"georeferenced: {ef.crs} (UTM metres), GeoJSON in WGS84 lon/lat"
            if ef is not None
            else LOCAL_FRAME_TEXT
        ),
        # the datum of every absolute height (cloud.ply z, trajectory heights); residuals and
        # defect depths are relative to the local road surface
        "vertical_datum": vertical_datum(cfg.mapping, drive, ef is not None),
        # what every length and depth is scaled by (α = h / d_c): with GPS the fixes check it
        "metric_scale": (
            "camera.yaml height_m, checked against the GPS track"
            if ef is not None
            else f"camera.yaml height_m ({drive.camera.height_m:g} m) alone (no GPS): every "
            "length, area and depth scales with it (5 % off in height_m is 5 % off in depth)"
        ),
        "reference": traj.reference.to_dict() if traj is not None and traj.reference else None,
        "counts": {
            "frames": len(drive.frames),
            "gps_fixes": len(drive.gps) if drive.gps is not None else 0,
            "pairs": len(pairs),
            "pairs_ok": sum(1 for p in pairs if p.ok),
            "pairs_failed": len(failed),  # of which the vehicle stood still (no depth):
            "pairs_still": sum(1 for p in pairs if p.status == STATUS_NO_MOTION),
            "posed_frames": len(traj) if traj is not None else 0,
        },
        "skipped_frames": [dataclasses.asdict(s) for s in drive.skipped],
        "camera_mask": drive.camera.mask and drive.camera.mask.to_report(),  # null: none
        "failed_pairs": failed,
        "warnings": [*drive.warnings, *filter(None, [failures_warning(pairs, out)])],
        "timings_s": timings,
        "versions": _versions(),
        "config": {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)},
    }
    pose_rep = out / rf.POSES_REPORT
    if traj is not None and pose_rep.is_file():
        report["poses"] = read_json(pose_rep)
        report["warnings"] += report["poses"].get("warnings", [])
        report["counts"]["segments"] = report["poses"].get("n_segments", 1)
        report["camera_mount"] = report["poses"].get("mount")
        report["counts"]["gps_outliers"] = len(report["poses"].get("gps_outliers", []))
    if products is not None and hasattr(products, "to_report"):
        report["map"] = products.to_report()
        report["warnings"] += list(report["map"].get("warnings") or [])
    if detections is not None and hasattr(detections, "to_report"):
        report["detection"] = detections.to_report()
        report["warnings"] += list(report["detection"].get("warnings") or [])
    return report
