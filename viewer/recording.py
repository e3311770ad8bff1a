"""Log a run folder to a Rerun recording (``log_run``); ``blueprint`` lays it out.

Entity tree (all 3D in local ENU metres, x east, y north, z up; see docs/viewer.md):

- ``world/cloud``            global point cloud coloured by residual_m (diverging colormap)
- ``world/defects``          defect outlines at the road surface, labelled id/type/depth/area/severity
- ``world/defect_boxes``     depth boxes of each defect (outline bbox x max depth)
- ``world/trajectory``       fused camera path; ``world/gps`` GPS fixes in ENU
- ``world/frusta/f<idx>``    static camera frusta every ``frustum_stride`` frames
- ``world/camera``           current camera (timeline): pose + pinhole; ``world/camera/image`` the
                             frame, with ``matches``, ``rejected``, ``defect_points``,
                             ``defect_outlines`` (map defects projected in), ``mask``
- ``map/*``                  GeoLineStrings / GeoPoints for the map view (tiles are the viewer's)
- ``mosaic/*``, ``surface/*``  ortho-mosaic and residual surface images with defect outlines
- ``frames/*``               per-frame scalars (p_defect, matches, inliers) and a frame card
- ``profiles/<id>``          depth profile of each defect along its long axis (bar chart)
- ``legend``, ``summary``, ``log``  colour legend, run summary, warnings (failed pairs)

The static entities are logged by ``scene``, the frame timeline by ``timeline``.
"""

from __future__ import annotations

import rerun as rr

from roadsurf.io.formats import LOCAL_FRAME_TEXT
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.rundata import RunData, depth_text
from roadsurf.viewer.scene import log_cloud, log_defects, log_mosaic, log_trajectory
from roadsurf.viewer.timeline import log_frames

APP_ID = "roadsurf"


def log_setup(rec: rr.RecordingStream) -> None:
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)


def summary_markdown(data: RunData, counts: dict[str, int]) -> str:
    r = data.report
    c = r.get("counts", {})
    lines = [
        "# roadsurf run",
        f"- run folder: `{data.run_dir}`",
        f"- drive: `{r.get('drive', '?')}`",
        f"- CRS: {data.crs or LOCAL_FRAME_TEXT}",
        f"- frames: {c.get('frames', '?')}, posed: {counts.get('posed_frames', 0)}, "
        f"pairs ok/failed: {c.get('pairs_ok', '?')}/{c.get('pairs_failed', '?')}"
        + (f" ({c['pairs_still']} standing still)" if c.get("pairs_still") else ""),
        f"- cloud points shown: {counts.get('cloud_points', 0)}",
        f"- defects: {counts.get('defects', 0)}",
        "",
        "Colours: the cloud is coloured by residual height (red below the road, blue above; "
        "see the legend). Defects: red high, orange medium, yellow low severity.",
    ]
    if data.defects:
        lines += ["", "| id | type | depth mm | area m² | severity |", "|---|---|---|---|---|"]
        for d in data.defects[:50]:
            lines.append(
                f"| {d.id} | {d.type} | {depth_text(d.max_depth_m).removesuffix(' mm')} | "
                f"{d.area_m2:.3f} | {d.severity} |"
            )
    if data.missing:
        lines += ["", "Not in this run folder: " + ", ".join(data.missing)]
    return "\n".join(lines)


def log_run(rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig) -> dict[str, int]:
    """Log everything in ``data``; returns counts of what was logged."""
    log_setup(rec)
    counts = {
        "cloud_points": log_cloud(rec, data, cfg),
        "defects": log_defects(rec, data, cfg),
        "posed_frames": log_trajectory(rec, data, cfg),
        "mosaic": int(log_mosaic(rec, data, cfg)),
    }
    counts["frames"] = log_frames(rec, data, cfg)
    rec.log(
        "summary",
        rr.TextDocument(summary_markdown(data, counts), media_type=rr.MediaType.MARKDOWN),
        static=True,
    )
    return counts
