"""The run folder: the one owner of every artifact's name and path.

``roadsurf run DRIVE --out OUT`` writes everything below OUT under the names defined here; the
stages, the viewer and the evaluation find them through :class:`RunFolder` instead of spelling
file names. docs/formats.md describes each file's content.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from roadsurf.core.errors import RunFolderBusyError

# reconstruction
PAIRS_DIR = "pairs"  # one .npz per frame pair (PairResult)
FEATURES_DIR = "features"  # per-frame keypoint cache
PROBES_DIR = "probes"  # fused run: cheap audit probes of pairs
# poses
POSES_NPZ = "poses.npz"
REFERENCE_JSON = "reference.json"  # the local ENU frame's origin
POSES_REPORT = "poses_report.json"
TRAJECTORY_GEOJSON = "trajectory.geojson"
TRAJECTORY_CSV = "trajectory.csv"
# global map
MAP_REPORT = "map_report.json"
MAP_POINTS = "map_points.npz"
CLOUD_PLY = "cloud.ply"
SURFACE_NOBS = "surface_nobs"  # dense surface: samples fused per cell (.tif / .vrt / tiles)
SURFACE_SIGMA = "surface_sigma"  # dense surface: each cell's height σ (.tif / .vrt / tiles)
DENSE_SEAMS = "dense_seams.npz"  # dense surface: the pairs' samples where two or more met
SURFACE = "surface"  # surface.tif / surface.vrt / tiles/surface_*.tif
MOSAIC = "mosaic"
TILES_DIR = "tiles"
SURFACE_TIF = f"{SURFACE}.tif"
SURFACE_VRT = f"{SURFACE}.vrt"
MOSAIC_TIF = f"{MOSAIC}.tif"
MOSAIC_VRT = f"{MOSAIC}.vrt"
MOSAIC_PREVIEW = "mosaic_preview.png"
SURFACE_PREVIEW = "surface_preview.png"
# detection
MASKS_DIR = "masks"  # one 2D defect mask per frame
DEFECTS_GEOJSON = "defects.geojson"
DEFECTS_CSV = "defects.csv"
FRAME_LABELS_CSV = "frames.csv"  # per-frame labels (not the drive's frames.csv)
DETECTION_JSON = "detection.json"
SCREENING_JSON = "screening.json"  # fused run: CNN screening per frame
# run level
RUN_JSON = "run.json"  # which drive the run folder belongs to (refused for another drive)
RUN_LOCK = ".roadsurf.lock"  # held (flock) while a run works in the folder: one at a time
# written when the frames hold pixels that never change outside camera.yaml's mask
# (io.drive.staticpx): a suggestion in camera.yaml's mask convention, 0 = ignore
SUGGESTED_MASK_PNG = "suggested_mask.png"
REPORT_JSON = "report.json"
REPORT_HTML = "report.html"
RECORDING_RRD = "run.rrd"
LIVE_RRD = "live.rrd"
EVALUATION_JSON = "evaluation.json"
EVALUATION_MD = "evaluation.md"


def is_run_folder(path: str | Path) -> bool:
    """True when ``path`` holds a roadsurf run: its run.json (written first), or the report.json
    of a run older than run.json."""
    p = Path(path)
    return (p / RUN_JSON).is_file() or (p / REPORT_JSON).is_file()


def artifact_names() -> frozenset[str]:
    """Every file or folder name a run writes directly below its folder (``--out`` checks
    them before writing into a folder that is not yet a run)."""
    names = {v for k, v in globals().items() if k.isupper() and isinstance(v, str)}
    stems = (SURFACE, MOSAIC, SURFACE_NOBS, SURFACE_SIGMA)
    names |= {f"{s}{ext}" for s in stems for ext in (".tif", ".vrt")}
    return frozenset(names - set(stems))


def pair_filename(index_a: int, index_b: int) -> str:
    """``000012_000013.npz``: the pair of frames ``index_a``, ``index_b`` (capture order)."""
    return f"{index_a:06d}_{index_b:06d}.npz"


def fingerprint_path(artifact: Path) -> Path:
    """``X.fingerprint`` beside the cached artifact ``X.npz``: the fingerprint of what produced
    it (a pair, a probe)."""
    return artifact.with_suffix(".fingerprint")


def read_fingerprint(artifact: Path) -> str | None:
    """The fingerprint stored beside ``artifact``; None when there is none (written by older
    code, or never finished): the artifact must be recomputed."""
    try:
        return fingerprint_path(artifact).read_text().strip()
    except OSError:
        return None


def feature_filename(frame_index: int, tag: str) -> str:
    """``000012_sift4000_<digest>.npz``: one frame's keypoint cache; ``tag`` names the settings."""
    return f"{frame_index:06d}_{tag}.npz"


def probe_filename(index_a: int, index_b: int, digest: str) -> str:
    """``000012_000013_<digest>.npz``: a fused run's audit probe of one pair."""
    return f"{index_a:06d}_{index_b:06d}_{digest}.npz"


def tile_filename(kind: str, row: int, col: int) -> str:
    """``surface_0001_0002.tif``: one GeoTIFF tile of a tiled raster."""
    return f"{kind}_{row:04d}_{col:04d}.tif"


@dataclass(frozen=True)
class RunFolder:
    """Paths of a run's artifacts below ``root`` (nothing is created or read here)."""

    root: Path

    def __init__(self, root: str | Path) -> None:
        object.__setattr__(self, "root", Path(root))

    def path(self, name: str) -> Path:
        """Any artifact by its name constant, e.g. ``run.path(DEFECTS_GEOJSON)``."""
        return self.root / name

    @property
    def pairs_dir(self) -> Path:
        return self.root / PAIRS_DIR

    def pair(self, index_a: int, index_b: int) -> Path:
        return self.pairs_dir / pair_filename(index_a, index_b)

    @property
    def features_dir(self) -> Path:
        return self.root / FEATURES_DIR

    @property
    def probes_dir(self) -> Path:
        return self.root / PROBES_DIR

    @property
    def tiles_dir(self) -> Path:
        return self.root / TILES_DIR

    @property
    def masks_dir(self) -> Path:
        return self.root / MASKS_DIR

    def mask(self, frame_filename: str) -> Path:
        """The 2D defect mask of one frame (PNG, same stem as the image)."""
        return self.masks_dir / f"{Path(frame_filename).stem}.png"

    @property
    def report(self) -> Path:
        return self.root / REPORT_JSON

    @property
    def defects_geojson(self) -> Path:
        return self.root / DEFECTS_GEOJSON

    @property
    def frame_labels(self) -> Path:
        return self.root / FRAME_LABELS_CSV

    @property
    def surface_tif(self) -> Path:
        return self.root / SURFACE_TIF

    @property
    def surface_vrt(self) -> Path:
        return self.root / SURFACE_VRT

    @property
    def cloud_ply(self) -> Path:
        return self.root / CLOUD_PLY

    @property
    def poses_npz(self) -> Path:
        return self.root / POSES_NPZ

    @property
    def map_report(self) -> Path:
        return self.root / MAP_REPORT

    @property
    def map_points(self) -> Path:
        return self.root / MAP_POINTS


# folders this process holds the lock of (the CLI takes it before opening a live recording
# there, then the pipeline again): flock conflicts between two opens of one process
_HELD: set[str] = set()


@contextmanager
def run_folder_lock(root: str | Path) -> Iterator[None]:
    """Hold ``root``'s RUN_LOCK (an exclusive flock, released when the process ends, even by
    SIGKILL) while a run works there; RunFolderBusyError when another process holds it (two
    runs in one folder deleted each other's temporary files and did all the work twice).
    Re-entrant within a process. Where no lock can be taken (no fcntl, a file system without
    locks, a lock file another user owns in a shared folder, a read-only folder) the run goes
    on unlocked with a warning, as before locks: its own writes report what fails."""
    import errno
    import logging
    import os

    key = str(Path(root).resolve())
    if key in _HELD:
        yield
        return
    log = logging.getLogger(__name__)
    path = Path(root) / RUN_LOCK
    try:
        import fcntl
    except ImportError:  # not a POSIX system
        log.warning("%s: no file locks on this system; make sure one run at a time uses it", root)
        yield
        return
    fd = -1
    for flags in (os.O_RDWR | os.O_CREAT, os.O_RDONLY):  # flock needs no write access
        try:
            fd = os.open(path, flags, 0o664)
            break
        except OSError:
            continue
    if fd < 0:
        log.warning("%s: cannot open %s; running without the one-run lock", root, RUN_LOCK)
        yield
        return
    try:
        locked = True
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            raise RunFolderBusyError(
                f"{root}: another roadsurf run is working in this folder ({holder}); wait for "
                "it to finish (then run again to resume) or choose another --out"
            ) from None
        except OSError as e:
            if e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL):
                raise
            log.warning("%s: the file system has no locks (%s); one run at a time, please", root, e)
            locked = False
        if locked:
            try:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"pid {os.getpid()}".encode(), 0)
            except OSError:
                pass  # a read-only descriptor: the lock holds, the holder goes unnamed
            _HELD.add(key)
        try:
            yield
        finally:
            if locked:
                _HELD.discard(key)
                fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
