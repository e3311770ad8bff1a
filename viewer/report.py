"""``RUN/report.html``: one self-contained page (images embedded as base64 PNG) that a road
engineer can open or e-mail: drive summary, defects sorted by severity, depth histogram, mosaic
and surface previews with the defects outlined, the path, skipped frames, failed pairs and
timings. Every section copes with its input missing (no GPS, no defects, a partial run)."""

from __future__ import annotations

import datetime as dt
import html
import logging
from pathlib import Path

from roadsurf.core.atomic import write_text_atomic
from roadsurf.core.errors import RoadsurfError
from roadsurf.io.runfolder import REPORT_HTML, REPORT_JSON, RUN_JSON, is_run_folder
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.report_figures import evidence_section, figures_section
from roadsurf.viewer.report_sections import (
    defects_section,
    problems_section,
    provenance_section,
    summary_section,
    timings_section,
)
from roadsurf.viewer.rundata import RunData
from roadsurf.viewer.runfolder import load_run

log = logging.getLogger(__name__)

CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,Helvetica,Arial,sans-serif;margin:0;
 background:#f4f5f7;color:#1d2330}
header{background:#1d2330;color:#fff;padding:18px 28px}
header h1{margin:0;font-size:22px} header p{margin:4px 0 0;color:#b8c0d0;font-size:13px}
main{padding:18px 28px;max-width:1300px}
section{background:#fff;border-radius:8px;padding:14px 18px;margin:0 0 16px;
 box-shadow:0 1px 3px rgba(0,0,0,.08)}
h2{font-size:17px;margin:0 0 10px}
table{border-collapse:collapse;font-size:13px;width:100%}
th,td{border-bottom:1px solid #e3e6eb;padding:4px 8px;text-align:left}
th{background:#f0f2f5} td.num{text-align:right;font-variant-numeric:tabular-nums}
.cards{display:flex;flex-wrap:wrap;gap:10px}
.card{background:#f0f2f5;border-radius:6px;padding:8px 14px;min-width:120px}
.card b{display:block;font-size:20px} .card span{font-size:12px;color:#556}
.sev{display:inline-block;padding:1px 8px;border-radius:10px;color:#000;font-size:12px}
.grid{display:flex;flex-wrap:wrap;gap:16px} .grid figure{margin:0;flex:1 1 560px}
figure img{max-width:100%;border:1px solid #e3e6eb;border-radius:4px}
figcaption{font-size:12px;color:#556} .muted{color:#778;font-size:13px}
"""


def write_report(
    run_dir: str | Path,
    out: str | Path | None = None,
    *,
    drive_dir: str | Path | None = None,
    cfg: ViewerConfig | None = None,
) -> Path:
    """Build the HTML report of a run folder; returns its path (default RUN/report.html)."""
    cfg = cfg or ViewerConfig()
    rd = Path(run_dir)
    if rd.is_dir() and not is_run_folder(rd):
        raise RoadsurfError(
            f"{rd}: not a roadsurf run folder (no {REPORT_JSON}, no {RUN_JSON}); give the "
            "--out folder of `roadsurf run`"
        )
    data = load_run(run_dir, drive_dir, max_raster_side_px=cfg.max_mosaic_side_px)
    out = Path(out) if out is not None else Path(run_dir) / REPORT_HTML
    write_text_atomic(out, render_report(data, cfg))
    log.info("wrote %s", out)
    return out


def render_report(data: RunData, cfg: ViewerConfig) -> str:
    import matplotlib

    matplotlib.use("Agg")
    parts = [
        summary_section(data),
        defects_section(data, cfg),
        evidence_section(data),
        figures_section(data, cfg),
        problems_section(data),
        timings_section(data),
        provenance_section(data),
    ]
    title = f"roadsurf report: {html.escape(data.run_dir.name)}"
    now = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    return (
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>{title}</title><style>{CSS}</style></head><body>"
        f"<header><h1>{title}</h1><p>Run folder {html.escape(str(data.run_dir.resolve()))} · "
        f"generated {now}</p></header><main>{''.join(parts)}</main></body></html>\n"
    )


def report_command(
    run_dir: str | Path,
    out: str | Path | None = None,
    *,
    drive_dir: str | Path | None = None,
    screenshot_png: str | Path | None = None,
) -> tuple[Path, Path | None]:
    """`roadsurf report`: write the report, optionally photograph it with headless Chromium."""
    path = write_report(run_dir, out, drive_dir=drive_dir)
    shot = None
    if screenshot_png is not None:
        from roadsurf.viewer.browser import screenshot

        shot = screenshot(path.resolve().as_uri(), screenshot_png, size=(1300, 2000)).path
    return path, shot
