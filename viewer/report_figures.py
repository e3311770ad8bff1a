"""The figures of the HTML report (embedded base64 images): image evidence of the most
severe defects, depth and residual histograms, depth profiles, the path, the mosaic and the
surface with the defects outlined."""

from __future__ import annotations

import base64
import io
import math
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.viewer.colors import residual_half_range_m
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.derived import defect_rings_3d, gps_enu_m, project_to_image, rowcol_from_enu
from roadsurf.viewer.profile import depth_profile
from roadsurf.viewer.report_sections import esc, fmt
from roadsurf.viewer.rundata import Raster, RunData, severity_rank, severity_rgb

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def evidence_section(data: RunData, n_max: int = 8, width_px: int = 360) -> str:
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
            cap = f"#{d.id} {d.type}, {fmt(d.max_depth_m, 1000)} mm, {d.severity} — {f.filename}"
            cells.append(
                f"<figure style='flex:0 0 {width_px}px'><img alt='{esc(cap)}' "
                f"src='data:image/jpeg;base64,{b64}'><figcaption>{esc(cap)}</figcaption></figure>"
            )
            break
    if not cells:
        return ""
    return (
        "<section><h2>Image evidence (most severe first)</h2>"
        "<p class='muted'>The frame taken nearest each defect, with the measured outline "
        f"projected in using the fused pose.</p><div class='grid'>{''.join(cells)}</div></section>"
    )


def _png(fig: Figure) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _figure(b64: str, caption: str) -> str:
    return (
        f"<figure><img alt='{esc(caption)}' src='data:image/png;base64,{b64}'>"
        f"<figcaption>{esc(caption)}</figcaption></figure>"
    )


def figures_section(data: RunData, cfg: ViewerConfig) -> str:
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
    # cracks kept on the images alone have no depth (NaN): not in the histogram
    measured = [d for d in data.defects if math.isfinite(d.max_depth_m)]
    depths = np.array([1000 * d.max_depth_m for d in measured])
    if depths.size:
        sevs = sorted({d.severity for d in measured}, key=severity_rank)
        bins = np.histogram_bin_edges(depths, bins=min(20, max(5, depths.size)))
        stack = [[1000 * d.max_depth_m for d in measured if d.severity == s] for s in sevs]
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


def _raster_plot(data: RunData, raster: Raster, kind: str, cfg: ViewerConfig) -> str:
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
