"""The text sections of the HTML report: drive summary, defect table, skipped frames and
failed pairs, timings and provenance; plus the small HTML helpers the figures share."""

from __future__ import annotations

import html
import math

import numpy as np

from roadsurf.io.formats import LOCAL_FRAME_TEXT
from roadsurf.io.runfolder import DEFECTS_CSV, DEFECTS_GEOJSON, REPORT_JSON
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.rundata import RunData, severity_rank, severity_rgb


def esc(v: object) -> str:
    return html.escape(str(v))


def fmt(v: float, scale: float = 1.0, nd: int = 1) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v * scale:.{nd}f}"


def card(value: object, label: str) -> str:
    return f"<div class='card'><b>{esc(value)}</b><span>{esc(label)}</span></div>"


def _path_length_m(data: RunData) -> float:
    """Length of the posed path (m) within its segments: the steps between two segments (their
    relative placement a guess, no vision nor GPS between them) are not road driven."""
    t = data.trajectory
    if t is None or len(t) < 2:
        return math.nan
    step = np.linalg.norm(np.diff(t.positions_enu_m[:, :2], axis=0), axis=1)
    if t.segment is not None:
        step = step[np.diff(np.asarray(t.segment)) == 0]
    return float(np.sum(step))


def summary_section(data: RunData) -> str:
    r = data.report
    c = r.get("counts", {})
    sev_counts: dict[str, int] = {}
    for d in data.defects:
        sev_counts[d.severity] = sev_counts.get(d.severity, 0) + 1
    cards = [
        card(c.get("frames", len(data.drive.frames) if data.drive else "?"), "frames"),
        card(len(data.trajectory) if data.trajectory is not None else 0, "posed frames"),
        card(fmt(_path_length_m(data), 1, 1) + " m", "path length"),
        card(c.get("gps_fixes", "?"), "GPS fixes"),
        card(f"{c.get('pairs_ok', '?')}/{c.get('pairs', '?')}", "pairs reconstructed"),
        card(len(data.defects), "defects"),
    ]
    for sev in sorted(sev_counts, key=lambda s: -severity_rank(s)):
        cards.append(card(sev_counts[sev], f"{sev} severity"))
    ref = data.reference
    rows = [
        ("Drive", r.get("drive", "unknown")),
        ("Method", r.get("method", "?")),
        ("CRS of exports", data.crs or f"none: {LOCAL_FRAME_TEXT}"),
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
            ("surface_model_px", "of which road model (seen once)", lambda v: f"{int(v):,}"),
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
    table = "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in rows)
    return (
        f"<section><h2>Drive summary</h2><div class='cards'>{''.join(cards)}</div>"
        f"<table style='margin-top:12px'>{table}</table></section>"
    )


def _sev_badge(sev: str) -> str:
    r, g, b = severity_rgb(sev)
    return f"<span class='sev' style='background:rgb({r},{g},{b})'>{esc(sev)}</span>"


def defects_section(data: RunData, cfg: ViewerConfig) -> str:
    if not data.defects:
        why = (
            f"{DEFECTS_GEOJSON} is missing (detection did not run)"
            if DEFECTS_GEOJSON in data.missing
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
            f"<tr><td class='num'>{k}</td><td>{esc(d.id)}</td><td>{esc(d.type)}</td>"
            f"<td>{_sev_badge(d.severity)}</td>"
            f"<td class='num'>{fmt(d.max_depth_m, 1000)}</td>"
            f"<td class='num'>{fmt(d.mean_depth_m, 1000)}</td>"
            f"<td class='num'>{fmt(d.area_m2, 1, 3)}</td>"
            f"<td class='num'>{fmt(d.volume_m3, 1000, 2)}</td>"
            f"<td class='num'>{fmt(d.length_m, 1, 2)} × {fmt(d.width_m, 1, 2)}</td>"
            f"<td class='num'>{fmt(d.confidence, 1, 2)}</td><td>{esc(where)}</td></tr>"
        )
    more = len(data.defects) - cfg.report_max_defects
    note = f"<p class='muted'>{more} more not listed (see {DEFECTS_CSV}).</p>" if more > 0 else ""
    return (
        f"<section><h2>Defects ({len(data.defects)}, most severe first)</h2>"
        f"<table id='defects'>{head}{''.join(rows)}</table>{note}</section>"
    )


def problems_section(data: RunData) -> str:
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
            f"<tr><td>{esc(s.get('file'))}</td><td>{esc(s.get('line') or '')}</td>"
            f"<td>{esc(s.get('reason'))}</td></tr>"
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
            f"<tr><td>{esc(f.get('frame_a'))}</td><td>{esc(f.get('frame_b'))}</td>"
            f"<td>{esc(f.get('status'))}</td><td>{esc(f.get('reason'))}</td></tr>"
            for f in failed
        ]
        out.append("</table>")
    else:
        out.append("<p class='muted'>No failed pairs.</p>")
    warns = r.get("warnings") or []
    if warns:
        out.append("<h2 style='margin-top:12px'>Warnings</h2><ul>")
        out += [f"<li>{esc(w)}</li>" for w in warns]
        out.append("</ul>")
    out.append("</section>")
    return "".join(out)


def timings_section(data: RunData) -> str:
    t = data.report.get("timings_s") or {}
    if not t:
        return (
            f"<section><h2>Timings</h2><p class='muted'>{REPORT_JSON} has no timings.</p></section>"
        )
    total = float(t.get("total", sum(v for k, v in t.items() if k != "total")) or 0.0)
    rows = []
    for k, v in t.items():
        share = f"{100 * float(v) / total:.0f} %" if total > 0 and k != "total" else ""
        rows.append(
            f"<tr><td>{esc(k)}</td><td class='num'>{float(v):.2f}</td>"
            f"<td class='num'>{share}</td></tr>"
        )
    return (
        "<section><h2>Timings</h2><table id='timings'><tr><th>stage</th><th>seconds</th>"
        f"<th>share</th></tr>{''.join(rows)}</table></section>"
    )


def provenance_section(data: RunData) -> str:
    v = data.report.get("versions") or {}
    items = ", ".join(f"{esc(k)} {esc(x)}" for k, x in v.items()) or "unknown"
    miss = ", ".join(esc(m) for m in data.missing) or "none"
    return (
        f"<section><h2>Provenance</h2><p class='muted'>Software: {items}.</p>"
        f"<p class='muted'>Not in the run folder: {miss}.</p></section>"
    )
