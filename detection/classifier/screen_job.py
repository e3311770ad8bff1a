"""CNN screening in a worker process, started first thing in a fused run.

Importing torch takes 1.3-2 s of one core on the 2-core bench machine, more than screening a
200-frame drive (~1 s). In its own process that import and the model load run on the second
core while the pipeline reads the drive and imports its own stages (SciPy, rasterio, Shapely,
scikit-image: ~1 s); threads could not overlap them, since imports hold the GIL. The pipeline
process of a fused run never imports torch.

The worker is ``python -m roadsurf.detection.classifier.screen_job RESULT HEADER``: the header
(JSON: model path, classifier settings) comes on the command line, so the worker imports torch and
loads the model at once; the frames follow on stdin when the pipeline has read the drive. It
logs and shows its progress bar on the shared stderr, and writes
``{"probs": {filename: p_defect}}`` or ``{"error": {...}}`` to the result file the parent
names. ``ScreeningJob.result`` raises an error as the same exception class (a corrupt model
file stays a ``ModelFileError``). The probabilities are those of ``screen_frames`` in-process
(same code; test).

No worker outlives its run: the parent kills it when the run stops (``close``, reached on
SIGTERM too, which the CLI turns into an exception), and the worker watches its parent and exits,
removing the job's temporary folder, when the parent is gone (``kill -9``). The folder is named
``roadsurf-screen-<parent pid>-*``, so the next job removes folders whose parent died.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core import errors
from roadsurf.core.atomic import write_json_atomic
from roadsurf.core.config import from_dict, to_dict
from roadsurf.core.errors import RoadsurfError
from roadsurf.core.imagemask import ImageMask
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.io.drive import Frame

log = logging.getLogger(__name__)

# exception classes a worker error may name; anything else comes back as RoadsurfError
_ERRORS: dict[str, type[RoadsurfError]] = {
    c.__name__: c
    for c in vars(errors).values()
    if isinstance(c, type) and issubclass(c, RoadsurfError)
}
_LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
TMP_PREFIX = "roadsurf-screen-"  # + "<parent pid>-<random>", in the system temporary folder
_WATCH_PARENT_S = 0.2  # how often the worker checks that its parent still runs


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except OSError:  # no such signal support (not POSIX): assume alive, keep the folder
        return True
    return True


def remove_stale_folders(tmp_root: str | Path | None = None) -> list[Path]:
    """Remove the temporary folders of screening jobs whose parent process is gone (a run
    killed with ``kill -9`` while its worker was starting); returns them."""
    root = Path(tmp_root if tmp_root is not None else tempfile.gettempdir())
    gone = []
    for d in root.glob(f"{TMP_PREFIX}*"):
        pid = d.name[len(TMP_PREFIX) :].split("-", 1)[0]
        if d.is_dir() and pid.isdigit() and not _pid_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)
            if not d.exists():
                gone.append(d)
    for d in gone:
        log.info("removed %s, left by a stopped run", d)
    return gone


class ScreeningJob:
    """A screening in a worker process: start it (the worker imports torch and loads the model
    at once), ``send`` it the frames when the drive is read, and ``result()`` waits for it.

    Use it as a context manager (or call ``close``): a job that is not waited for is killed, so
    an interrupted or failed run leaves no worker behind.
    """

    def __init__(
        self, model_path: str | Path, cfg: ClassifierConfig | None = None, *, progress: bool = True
    ) -> None:
        cfg = cfg or ClassifierConfig()
        self.model_path = Path(model_path)
        remove_stale_folders()
        self._tmp = tempfile.TemporaryDirectory(prefix=f"{TMP_PREFIX}{os.getpid()}-")
        self._out = Path(self._tmp.name) / "result.json"
        header = {
            "model": str(self.model_path),
            "config": to_dict(cfg),
            "progress": bool(progress),
            "log_level": logging.getLogger().getEffectiveLevel(),
            "parent_pid": os.getpid(),
        }
        # the worker imports this very checkout, whatever the current directory or sys.path
        root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        self._proc: subprocess.Popen[bytes] | None = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "roadsurf.detection.classifier.screen_job",
                str(self._out),
                json.dumps(header),
            ],
            stdin=subprocess.PIPE,
            env=env,
        )
        self._sent = False

    def send(self, frames: Sequence[Frame], mask: ImageMask | None = None) -> None:
        """The frames to screen, in capture order, and the camera's image mask (once)."""
        if self._proc is None or self._sent:
            raise RoadsurfError("this screening job is closed or already has its frames")
        self._sent = True
        rows = [[f.index, f.filename, str(f.path), f.timestamp_s] for f in frames]
        mask_file = None
        if mask is not None:  # the pixels travel as a .npy in the job's folder
            mask_file = str(Path(self._tmp.name) / "mask.npy")
            np.save(mask_file, mask.usable)
        payload = {"frames": rows, "mask": mask_file, "mask_source": mask.source if mask else ""}
        try:
            if self._proc.stdin is not None:
                self._proc.stdin.write(json.dumps(payload).encode())
                self._proc.stdin.close()
        except OSError:  # the worker stopped early (e.g. a bad model file): result() says why
            pass

    def result(self) -> dict[str, float]:
        """{filename: p_defect} once the worker is done; raises its error (ModelFileError, ...)
        or a RoadsurfError when it died without one."""
        if self._proc is None or not self._sent:
            raise RoadsurfError("this screening job is closed or was never sent its frames")
        rc = self._proc.wait()
        self._proc = None
        try:
            data = json.loads(self._out.read_text()) if self._out.is_file() else None
        finally:
            self._tmp.cleanup()
        if isinstance(data, dict) and isinstance(data.get("probs"), dict):
            return {str(k): float(v) for k, v in data["probs"].items()}
        err = data.get("error") if isinstance(data, dict) else None
        if isinstance(err, dict):
            cls = _ERRORS.get(str(err.get("type")), RoadsurfError)
            raise cls(str(err.get("message")))
        raise RoadsurfError(
            f"CNN screening with {self.model_path} stopped (worker exit status {rc}) without a "
            "result; its messages are above. Set `classifier: {screen_in_subprocess: false}` "
            "in the run config to screen in the pipeline's own process."
        )

    @property
    def pid(self) -> int | None:
        """The worker's process id while it is not waited for (None after result/close)."""
        return None if self._proc is None else self._proc.pid

    def close(self) -> None:
        """Kill the worker if it still runs, and remove its files."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        self._tmp.cleanup()

    def __enter__(self) -> ScreeningJob:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _work(out: Path, header: dict[str, Any]) -> int:
    sent: dict[str, Any] = {}

    def frames() -> list[Frame]:  # blocks until the parent has read the drive
        sent.update(json.loads(sys.stdin.read()))
        return [Frame(int(i), str(fn), Path(p), float(t)) for i, fn, p, t in sent["frames"]]

    def mask() -> ImageMask | None:  # called after frames()
        path = sent.get("mask")
        return ImageMask(np.load(path), str(sent.get("mask_source", ""))) if path else None

    try:
        from roadsurf.detection.classifier.screen import screen_frames

        cfg = from_dict(ClassifierConfig, header["config"], "classifier")
        probs = screen_frames(
            header["model"], frames, cfg, progress=bool(header["progress"]), mask=mask
        )
    except RoadsurfError as e:
        write_json_atomic(out, {"error": {"type": type(e).__name__, "message": str(e)}})
        return 2
    except Exception as e:  # noqa: BLE001 - reported to the parent, which raises it
        log.exception("CNN screening failed")
        msg = f"CNN screening failed: {type(e).__name__}: {e} (traceback above)"
        write_json_atomic(out, {"error": {"type": "RoadsurfError", "message": msg}})
        return 1
    write_json_atomic(out, {"probs": probs})
    return 0


def _parent_gone(parent_pid: int | None) -> bool:
    return parent_pid is not None and os.getppid() != parent_pid


def _watch_parent(parent_pid: int, folder: Path) -> None:
    """Exit, removing the job's folder, as soon as the parent process is gone (killed with
    ``kill -9``, or ended without closing the job): the worker is reparented then."""
    while not _parent_gone(parent_pid):
        time.sleep(_WATCH_PARENT_S)
    shutil.rmtree(folder, ignore_errors=True)
    os._exit(143)


def main(argv: list[str] | None = None) -> int:
    """Worker entry point: ``python -m roadsurf.detection.classifier.screen_job RESULT_JSON
    HEADER_JSON``, then the frames on stdin."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        sys.stderr.write(
            "usage: python -m roadsurf.detection.classifier.screen_job RESULT HEADER < frames\n"
        )
        return 2
    header = json.loads(args[1])
    logging.basicConfig(
        level=int(header.get("log_level", logging.INFO)), format=_LOG_FORMAT, datefmt="%H:%M:%S"
    )
    out = Path(args[0])
    parent = header.get("parent_pid")
    parent_pid = int(parent) if parent is not None else None
    if parent_pid is not None:
        threading.Thread(
            target=_watch_parent, args=(parent_pid, out.parent), name="watch-parent", daemon=True
        ).start()
    try:
        return _work(out, header)
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group; the parent reports it
        return 130
    finally:
        if _parent_gone(parent_pid):  # nobody will read the result: leave nothing behind
            shutil.rmtree(out.parent, ignore_errors=True)


if __name__ == "__main__":
    code = main()
    # the result is on disk: skip the interpreter's teardown (unloading torch takes ~0.6 s,
    # which the parent would wait for, or share a core with)
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
