"""``RUN/report.html``: one self-contained page (images embedded as base64 PNG) that a road
engineer can open or e-mail: drive summary, defects sorted by severity, depth histogram, mosaic
and surface previews with the defects outlined, the path, skipped frames, failed pairs and
timings. Every section copes with its input missing (no GPS, no defects, a partial run)."""

from __future__ import annotations

import base64
import datetime as dt
import html
import io
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import write_text_atomic
from roadsurf.viewer.colors import residual_half_range_m
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.runfolder import (
    RunData,
    defect_rings_3d,
    depth_profile,
    gps_enu_m,
    load_run,
    project_to_image,
    rowcol_from_enu,
    severity_rank,
    severity_rgb,
)

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
    data = load_run(run_dir, drive_dir, max_raster_side_px=cfg.max_mosaic_side_px)
    out = Path(out) if out is not None else Path(run_dir) / "report.html"
    write_text_atomic(out, render_report(data, cfg))
    log.info("wrote %s", out)
    return out


def render_report(data: RunData, cfg: ViewerConfig) -> str:
    import matplotlib

    matplotlib.use("Agg")
    parts = [
        _summary(data),
        _defect_table(data, cfg),
        _evidence(data),
        _figures(data, cfg),
        _problems(data),
        _timings(data),
        _provenance(data),
    ]
    title = f"roadsurf report: {html.escape(data.run_dir.name)}"
    now = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    return (
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>{title}</title><style>{CSS}</style></head><body>"
        f"<header><h1>{title}</h1><p>Run folder {html.escape(str(data.run_dir.resolve()))} · "
        f"generated {now}</p></header><main>{''.join(parts)}</main></body></html>\n"
    )


# --------------------------------------------------------------------------- sections


def _esc(v: Any) -> str:
    return html.escape(str(v))


def _fmt(v: float, scale: float = 1.0, nd: int = 1) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v * scale:.{nd}f}"


def _card(value: Any, label: str) -> str:
    return f"<div class='card'><b>{_esc(value)}</b><span>{_esc(label)}</span></div>"


def _path_length_m(data: RunData) -> float:
    t = data.trajectory
    if t is None or len(t) < 2:
        return math.nan
    return float(np.sum(np.linalg.norm(np.diff(t.positions_enu_m[:, :2], axis=0), axis=1)))


def _summary(data: RunData) -> str:
    r = data.report
    c = r.get("counts", {})
    sev_counts: dict[str, int] = {}
    for d in data.defects:
        sev_counts[d.severity] = sev_counts.get(d.severity, 0) + 1
    cards = [
        _card(c.get("frames", len(data.drive.frames) if data.drive else "?"), "frames"),
        _card(len(data.trajectory) if data.trajectory is not None else 0, "posed frames"),
        _card(_fmt(_path_length_m(data), 1, 1) + " m", "path length"),
        _card(c.get("gps_fixes", "?"), "GPS fixes"),
        _card(f"{c.get('pairs_ok', '?')}/{c.get('pairs', '?')}", "pairs reconstructed"),
        _card(len(data.defects), "defects"),
    ]
    for sev in sorted(sev_counts, key=lambda s: -severity_rank(s)):
        cards.append(_card(sev_counts[sev], f"{sev} severity"))
    ref = data.reference
    rows = [
        ("Drive", r.get("drive", "unknown")),
        ("Method", r.get("method", "?")),
        ("CRS of exports", data.crs or "none: local ENU metres (no GPS)"),
        (
            "ENU reference",
            f"lat {ref.lat_deg:.7f}, lon {ref.lon_deg:.7f}, alt {ref.alt_m:.2f} m"
            if ref
            else "none",
        ),
    ]
    m = r.get("map") or {}
    map_bits = [
        f"{label} {fmt(m[key])}"
        for key, label, fmt in (
            ("gsd_m", "GSD", lambda v: f"{1000 * float(v):.1f} mm"),
            ("n_points", "points", lambda v: f"{int(v):,}"),
            ("surface_px", "surface pixels", lambda v: f"{int(v):,}"),
            ("mosaic_px", "mosaic pixels", lambda v: f"{int(v):,}"),
        )
        if isinstance(m.get(key), (int, float))
    ]
    if map_bits:
        rows.append(("Map", " · ".join(map_bits)))
    det = r.get("detection") or {}
    if isinstance(det.get("noise_m"), (int, float)):
        rows.append(
            (
                "Detection",
                f"road noise σ {1000 * det['noise_m']:.2f} mm"
                + (
                    f", depth threshold T_d {1000 * det['seed_threshold_m']:.1f} mm"
                    if isinstance(det.get("seed_threshold_m"), (int, float))
                    else ""
                ),
            )
        )
    table = "".join(f"<tr><th>{_esc(k)}</th><td>{_esc(v)}</td></tr>" for k, v in rows)
    return (
        f"<section><h2>Drive summary</h2><div class='cards'>{''.join(cards)}</div>"
        f"<table style='margin-top:12px'>{table}</table></section>"
    )


def _sev_badge(sev: str) -> str:
    r, g, b = severity_rgb(sev)
    return f"<span class='sev' style='background:rgb({r},{g},{b})'>{_esc(sev)}</span>"


def _defect_table(data: RunData, cfg: ViewerConfig) -> str:
    if not data.defects:
        why = (
            "defects.geojson is missing (detection did not run)"
            if "defects.geojson" in data.missing
            else "no defects were found on this drive"
        )
        return f"<section><h2>Defects</h2><p class='muted'>None: {why}.</p></section>"
    head = (
        "<tr><th>#</th><th>id</th><th>type</th><th>severity</th><th>max depth mm</th>"
        "<th>mean depth mm</th><th>area m²</th><th>volume l</th><th>length × width m</th>"
        "<th>confidence</th><th>centroid</th></tr>"
    )
    rows = []
    for k, d in enumerate(data.defects[: cfg.report_max_defects], 1):
        if d.ring_lonlat is not None:
            lon, lat = (
                d.ring_lonlat[:-1].mean(axis=0) if len(d.ring_lonlat) > 1 else d.ring_lonlat[0]
            )
            where = f"{lat:.7f}, {lon:.7f}"
        else:
            e, n = d.centroid_enu_m
            where = f"E {e:.2f} m, N {n:.2f} m (local)"
        rows.append(
            f"<tr><td class='num'>{k}</td><td>{_esc(d.id)}</td><td>{_esc(d.type)}</td>"
            f"<td>{_sev_badge(d.severity)}</td>"
            f"<td class='num'>{_fmt(d.max_depth_m, 1000)}</td>"
            f"<td class='num'>{_fmt(d.mean_depth_m, 1000)}</td>"
            f"<td class='num'>{_fmt(d.area_m2, 1, 3)}</td>"
            f"<td class='num'>{_fmt(d.volume_m3, 1000, 2)}</td>"
            f"<td class='num'>{_fmt(d.length_m, 1, 2)} × {_fmt(d.width_m, 1, 2)}</td>"
            f"<td class='num'>{_fmt(d.confidence, 1, 2)}</td><td>{_esc(where)}</td></tr>"
        )
    more = len(data.defects) - cfg.report_max_defects
    note = f"<p class='muted'>{more} more not listed (see defects.csv).</p>" if more > 0 else ""
    return (
        f"<section><h2>Defects ({len(data.defects)}, most severe first)</h2>"
        f"<table id='defects'>{head}{''.join(rows)}</table>{note}</section>"
    )


def _evidence(data: RunData, n_max: int = 8, width_px: int = 360) -> str:
    """For the most severe defects: the frame taken closest above it, outline projected in."""
    t, drive = data.trajectory, data.drive
    if not data.defects or t is None or len(t) == 0 or drive is None:
        return ""
    import cv2

    frame_of = {f.index: f for f in drive.frames}
    pos = t.positions_enu_m[:, :2]
    cells = []
    for d, ring in defect_rings_3d(data)[:n_max]:
        order = np.argsort(np.sum((pos - d.centroid_enu_m) ** 2, axis=1))
        for k in order[:5]:  # the nearest frames whose image holds the outline
            f = frame_of.get(int(t.frame_indices[k]))
            uv = project_to_image(t.world_from_cam[k], drive.camera, ring) if f else None
            if uv is None:
                continue
            img = cv2.imread(str(f.path), cv2.IMREAD_COLOR)
            if img is None:
                continue
            r, g, b = severity_rgb(d.severity)
            pts = np.rint(uv).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(img, [pts], True, (b, g, r), max(2, img.shape[1] // 200), cv2.LINE_AA)
            scale = width_px / img.shape[1]
            img = cv2.resize(
                img, (width_px, max(1, round(img.shape[0] * scale))), interpolation=cv2.INTER_AREA
            )
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
            if not ok:
                continue
            b64 = base64.b64encode(buf.tobytes()).decode("ascii")
            cap = f"#{d.id} {d.type}, {_fmt(d.max_depth_m, 1000)} mm, {d.severity} — {f.filename}"
            cells.append(
                f"<figure style='flex:0 0 {width_px}px'><img alt='{_esc(cap)}' "
                f"src='data:image/jpeg;base64,{b64}'><figcaption>{_esc(cap)}</figcaption></figure>"
            )
            break
    if not cells:
        return ""
    return (
        "<section><h2>Image evidence (most severe first)</h2>"
        "<p class='muted'>The frame taken nearest each defect, with the measured outline "
        f"projected in using the fused pose.</p><div class='grid'>{''.join(cells)}</div></section>"
    )


def _png(fig: Any) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _figure(b64: str, caption: str) -> str:
    return (
        f"<figure><img alt='{_esc(caption)}' src='data:image/png;base64,{b64}'>"
        f"<figcaption>{_esc(caption)}</figcaption></figure>"
    )


def _figures(data: RunData, cfg: ViewerConfig) -> str:
    figs = [_depth_histogram(data), _path_plot(data)]
    if data.defects:
        figs.append(_profiles_plot(data, cfg))
    for raster, kind in ((data.mosaic, "mosaic"), (data.surface, "surface")):
        figs.append(
            _raster_plot(data, raster, kind, cfg)
            if raster is not None
            else f"<p class='muted'>No {kind}.tif in this run.</p>"
        )
    return f"<section><h2>Figures</h2><div class='grid'>{''.join(figs)}</div></section>"


def _depth_histogram(data: RunData) -> str:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    ax = axes[0]
    depths = np.array([1000 * d.max_depth_m for d in data.defects if math.isfinite(d.max_depth_m)])
    if depths.size:
        sevs = sorted({d.severity for d in data.defects}, key=severity_rank)
        bins = np.histogram_bin_edges(depths, bins=min(20, max(5, depths.size)))
        stack = [[1000 * d.max_depth_m for d in data.defects if d.severity == s] for s in sevs]
        ax.hist(
            stack,
            bins=bins,
            stacked=True,
            label=sevs,
            color=[np.array(severity_rgb(s)) / 255 for s in sevs],
        )
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no defects", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("max depth (mm)")
    ax.set_ylabel("defects")
    ax.set_title("Defect depth", fontsize=10)
    ax = axes[1]
    r = data.cloud_residual_m
    if r is not None and np.isfinite(r).any():
        rr_mm = 1000 * r[np.isfinite(r)]
        lo, hi = np.percentile(rr_mm, [0.1, 99.9])
        ax.hist(rr_mm, bins=80, range=(min(lo, -1), max(hi, 1)), color="#4a6fa5", log=True)
        ax.set_xlabel("residual height (mm, negative below the road)")
        ax.set_ylabel("points (log)")
    else:
        ax.text(0.5, 0.5, "no point cloud", ha="center", va="center", transform=ax.transAxes)
    ax.set_title("Surface residuals of the cloud", fontsize=10)
    fig.tight_layout()
    return _figure(_png(fig), "Depth histogram of the defects (left) and of all map points.")


def _profiles_plot(data: RunData, cfg: ViewerConfig, n_max: int = 6) -> str:
    import matplotlib.pyplot as plt

    shown = [(d, depth_profile(data, d, cfg.profile_samples)) for d in data.defects[:n_max]]
    shown = [(d, p) for d, p in shown if p is not None]
    if not shown:
        return (
            "<p class='muted'>No depth profiles: the cloud has no residuals near the defects.</p>"
        )
    cols = min(3, len(shown))
    rows = math.ceil(len(shown) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.3 * rows), squeeze=False)
    for ax in axes.ravel()[len(shown) :]:
        ax.axis("off")
    for ax, (d, (dist, res)) in zip(axes.ravel(), shown, strict=False):
        ax.plot(100 * dist, 1000 * res, "-", color=np.array(severity_rgb(d.severity)) / 255)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(f"#{d.id} {d.type}, {d.severity}", fontsize=9)
        ax.set_xlabel("along the long axis (cm)", fontsize=8)
        ax.set_ylabel("height (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    return _figure(
        _png(fig), "Depth profiles of the most severe defects (mean residual in a strip)."
    )


def _path_plot(data: RunData) -> str:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.2))
    t = data.trajectory
    drew = False
    gps = gps_enu_m(data)
    if gps is not None:
        ax.plot(gps[:, 0], gps[:, 1], ".", ms=4, color="#00a6d6", label="GPS fixes")
        drew = True
    if t is not None and len(t):
        p = t.positions_enu_m
        ax.plot(p[:, 0], p[:, 1], "-", lw=1.5, color="#2ca02c", label="fused trajectory")
        drew = True
    for d in data.defects:
        ring = d.ring_enu_m
        ax.fill(
            ring[:, 0],
            ring[:, 1],
            color=np.array(severity_rgb(d.severity)) / 255,
            alpha=0.7,
            lw=0.8,
            ec="k",
        )
        ax.annotate(d.id, d.centroid_enu_m, fontsize=7, ha="center")
        drew = True
    if not drew:
        ax.text(0.5, 0.5, "no trajectory", ha="center", va="center", transform=ax.transAxes)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m, local ENU)")
    ax.set_ylabel("north (m)")
    if drew:
        ax.legend(fontsize=8, loc="best")
    ax.set_title("Path and defects (local ENU)", fontsize=10)
    return _figure(_png(fig), "Fused camera path, GPS fixes and defect outlines.")


def _raster_plot(data: RunData, raster: Any, kind: str, cfg: ViewerConfig) -> str:
    import matplotlib.pyplot as plt

    h, w = raster.data.shape[:2]
    size = 7.0
    fig, ax = plt.subplots(figsize=(size * min(2.0, max(0.4, w / h)), size))
    if kind == "surface":
        half = residual_half_range_m(
            raster.data, cfg.residual_range_percentile, cfg.min_residual_range_m
        )
        im = ax.imshow(
            1000 * raster.data,
            cmap=cfg.colormap,
            vmin=-1000 * half,
            vmax=1000 * half,
            interpolation="nearest",
        )
        fig.colorbar(im, ax=ax, shrink=0.7, label="residual height (mm)")
        cap = "Surface residual (red below the road) with defect outlines."
    else:
        ax.imshow(raster.data, interpolation="nearest")
        cap = "Ortho-mosaic with defect outlines."
    for d in data.defects:
        rc = rowcol_from_enu(data, raster.grid, d.ring_enu_m)
        ax.plot(rc[:, 1], rc[:, 0], "-", lw=1.5, color=np.array(severity_rgb(d.severity)) / 255)
        c = rc.mean(axis=0)
        ax.text(
            c[1],
            c[0],
            d.id,
            fontsize=7,
            color="k",
            bbox={"boxstyle": "round,pad=0.1", "fc": "white", "alpha": 0.7, "lw": 0},
        )
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(f"{kind} ({raster.grid.gsd_m * 1000:.1f} mm/px shown)", fontsize=10)
    return _figure(_png(fig), cap)


def _problems(data: RunData) -> str:
    r = data.report
    skipped = r.get("skipped_frames") or []
    failed = r.get("failed_pairs")
    if failed is None:  # older or partial run: take them from the pair files
        failed = [
            {"frame_a": p.frame_a, "frame_b": p.frame_b, "status": p.status, "reason": p.reason}
            for p in data.pairs
            if not p.ok
        ]
    out = ["<section><h2>Skipped frames and failed pairs</h2>"]
    if skipped:
        out.append("<table id='skipped'><tr><th>file</th><th>line</th><th>reason</th></tr>")
        out += [
            f"<tr><td>{_esc(s.get('file'))}</td><td>{_esc(s.get('line') or '')}</td>"
            f"<td>{_esc(s.get('reason'))}</td></tr>"
            for s in skipped
        ]
        out.append("</table>")
    else:
        out.append("<p class='muted'>No skipped frames or GPS rows.</p>")
    if failed:
        out.append(
            "<table id='failed' style='margin-top:10px'><tr><th>frame a</th>"
            "<th>frame b</th><th>status</th><th>reason</th></tr>"
        )
        out += [
            f"<tr><td>{_esc(f.get('frame_a'))}</td><td>{_esc(f.get('frame_b'))}</td>"
            f"<td>{_esc(f.get('status'))}</td><td>{_esc(f.get('reason'))}</td></tr>"
            for f in failed
        ]
        out.append("</table>")
    else:
        out.append("<p class='muted'>No failed pairs.</p>")
    warns = r.get("warnings") or []
    if warns:
        out.append("<h2 style='margin-top:12px'>Warnings</h2><ul>")
        out += [f"<li>{_esc(w)}</li>" for w in warns]
        out.append("</ul>")
    out.append("</section>")
    return "".join(out)


def _timings(data: RunData) -> str:
    t = data.report.get("timings_s") or {}
    if not t:
        return "<section><h2>Timings</h2><p class='muted'>report.json has no timings.</p></section>"
    total = float(t.get("total", sum(v for k, v in t.items() if k != "total")) or 0.0)
    rows = []
    for k, v in t.items():
        share = f"{100 * float(v) / total:.0f} %" if total > 0 and k != "total" else ""
        rows.append(
            f"<tr><td>{_esc(k)}</td><td class='num'>{float(v):.2f}</td>"
            f"<td class='num'>{share}</td></tr>"
        )
    return (
        "<section><h2>Timings</h2><table id='timings'><tr><th>stage</th><th>seconds</th>"
        f"<th>share</th></tr>{''.join(rows)}</table></section>"
    )


def _provenance(data: RunData) -> str:
    v = data.report.get("versions") or {}
    items = ", ".join(f"{_esc(k)} {_esc(x)}" for k, x in v.items()) or "unknown"
    miss = ", ".join(_esc(m) for m in data.missing) or "none"
    return (
        f"<section><h2>Provenance</h2><p class='muted'>Software: {items}.</p>"
        f"<p class='muted'>Not in the run folder: {miss}.</p></section>"
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
