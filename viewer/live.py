"""Live streaming for `roadsurf run DRIVE --rerun`.

The CLI builds this observer (``make_observer``) and passes it to ``run_drive``, which calls
``observer(stage_name, result)`` after each stage (see roadsurf/pipeline/run.py); the pipeline
never imports the viewer. Each stage has written its artifacts to the run folder before it
returns, so the observer reads what is new from the folder with the same code as
`roadsurf view` and logs it: frames with their matches after reconstruction, the trajectory
and frusta after poses, the cloud and the mosaic after the global map, the defects after
detection, the summary at the end.

Where the native viewer can open (a display), it is spawned; otherwise the stream goes to
RUN/live.rrd and a warning says how to open it (`rerun RUN/live.rrd` or `roadsurf view --serve`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import rerun as rr

from roadsurf.core.errors import RoadsurfError
from roadsurf.io.runfolder import LIVE_RRD
from roadsurf.viewer.blueprint import blueprint, layout_for
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.recording import APP_ID, log_setup, summary_markdown
from roadsurf.viewer.rundata import RunData
from roadsurf.viewer.runfolder import load_run
from roadsurf.viewer.scene import log_cloud, log_defects, log_mosaic, log_trajectory
from roadsurf.viewer.timeline import log_camera_poses, log_frames

log = logging.getLogger(__name__)


class LiveObserver:
    """Callable ``(stage, result)`` that streams a running pipeline into Rerun."""

    def __init__(
        self,
        run_dir: str | Path,
        cfg: ViewerConfig | None = None,
        *,
        rec: rr.RecordingStream | None = None,
        spawn: bool = True,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.cfg = cfg or ViewerConfig()
        self.drive_dir: Path | None = None
        self.counts: dict[str, int] = {}
        self.rrd: Path | None = None
        self._spawn = spawn
        # connected at the first stage, once the run holds its folder: a run refused there
        # (another works in it) must not truncate that run's live.rrd
        self.rec: rr.RecordingStream | None = rec
        if rec is not None:
            log_setup(rec)

    def _stream(self) -> rr.RecordingStream:
        if self.rec is None:
            rec = rr.RecordingStream(APP_ID)
            self._connect(rec, self._spawn)
            log_setup(rec)
            self.rec = rec
        return self.rec

    def _connect(self, rec: rr.RecordingStream, spawn: bool) -> None:
        from roadsurf.viewer.api import spawn_native

        if spawn:
            try:
                spawn_native(rec, blueprint([]), hint=f"roadsurf view {self.run_dir}")
                return
            except RoadsurfError as e:
                log.warning("%s", e)
        self.rrd = self.run_dir / LIVE_RRD
        self.run_dir.mkdir(parents=True, exist_ok=True)
        rec.save(self.rrd, default_blueprint=blueprint([]))
        log.warning(
            "live recording goes to %s; open it with `rerun %s` (or `roadsurf view %s --serve`)",
            self.rrd,
            self.rrd,
            self.run_dir,
        )

    def _load(self) -> RunData:
        return load_run(
            self.run_dir, self.drive_dir, max_raster_side_px=self.cfg.max_mosaic_side_px
        )

    def __call__(self, stage: str, result: Any) -> None:
        # ``result`` is the stage's own output (the pipeline's Observer protocol); only the
        # drive's root is read here, everything else comes from the run folder
        rec, cfg = self._stream(), self.cfg
        if stage == "drive":
            self.drive_dir = Path(result.root)
        elif stage == "reconstruction":
            self.counts["frames"] = log_frames(rec, self._load(), cfg, with_poses=False)
        elif stage == "poses":
            data = self._load()
            self.counts["posed_frames"] = log_trajectory(rec, data, cfg)
            log_camera_poses(rec, data, cfg)
        elif stage == "globalmap":
            data = self._load()
            self.counts["cloud_points"] = log_cloud(rec, data, cfg)
            self.counts["mosaic"] = int(log_mosaic(rec, data, cfg))
        elif stage == "detection":
            data = self._load()
            self.counts["defects"] = log_defects(rec, data, cfg)
            rec.send_blueprint(layout_for(data))
        elif stage == "report":
            data = self._load()
            rec.log(
                "summary",
                rr.TextDocument(summary_markdown(data, self.counts), media_type="text/markdown"),
                static=True,
            )
            rec.flush()
            if self.rrd is not None:
                rec.disconnect()  # finish the file
            return
        else:
            return
        rec.flush()


def make_observer(run_dir: str | Path, cfg: ViewerConfig | None = None) -> LiveObserver:
    """The observer `roadsurf run --rerun` passes to the pipeline (the CLI imports this)."""
    return LiveObserver(run_dir, cfg)
