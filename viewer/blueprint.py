"""The default Rerun layout: the 3D map left; map / mosaic / surface tabs, the current frame and
the per-frame plots right, with the 3D eye and map zoom fitted to the run."""

from __future__ import annotations

import math

import numpy as np
import rerun.blueprint as rrb

from roadsurf.viewer.derived import gps_enu_m
from roadsurf.viewer.rundata import DefectView, RunData
from roadsurf.viewer.scene import entity_part

MAX_PROFILE_TABS = 6  # more defects still get a profile entity, just no tab of their own


def overview_eye(data: RunData) -> rrb.EyeControls3D | None:
    """A 3D camera that looks at the whole cloud (or path) obliquely from the south."""
    pts = data.cloud_enu_m
    if pts is None or len(pts) == 0:
        pts = data.trajectory.positions_enu_m if data.trajectory is not None else None
    if pts is None or len(pts) == 0:
        return None
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    centre = (lo + hi) / 2
    span = float(np.clip(np.max(hi[:2] - lo[:2]), 2.0, 40.0))
    return rrb.EyeControls3D(
        kind=rrb.Eye3DKind.Orbital,
        position=centre + np.array([0.0, -0.55 * span, 0.75 * span]),
        look_target=centre,
        eye_up=[0.0, 0.0, 1.0],
    )


def map_zoom(data: RunData, view_px: float = 400.0) -> float:
    """Web-map zoom level that fits the GPS track / path into about ``view_px`` pixels."""
    pts = gps_enu_m(data)
    if pts is None and data.trajectory is not None and len(data.trajectory):
        pts = data.trajectory.positions_enu_m
    if pts is None or len(pts) < 2 or data.reference is None:
        return 18.0
    extent = max(5.0, float(np.max(np.ptp(pts[:, :2], axis=0))))
    m_per_px_z0 = 156543.03 * math.cos(math.radians(data.reference.lat_deg))
    return float(np.clip(math.log2(m_per_px_z0 * view_px / extent), 3.0, 19.0))


def layout_for(data: RunData) -> rrb.Blueprint:
    """The default blueprint fitted to a run (3D eye over the cloud, map zoom over the track)."""
    return blueprint(data.defects, overview_eye(data), map_zoom(data))


def blueprint(
    defects: list[DefectView] | None = None,
    eye: rrb.EyeControls3D | None = None,
    zoom: float = 18.0,
) -> rrb.Blueprint:
    """Default layout: 3D map left; map / mosaic tabs, current frame and plots right."""
    profile_tabs = [
        rrb.BarChartView(name=f"Profile #{d.id} (mm)", origin=f"profiles/{entity_part(d.id)}")
        for d in (defects or [])[:MAX_PROFILE_TABS]
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(
                    name="3D map (ENU m, residual colours)",
                    origin="world",
                    contents=["+ world/**", "- world/cloud_rgb"],
                    eye_controls=eye,
                    background=[28, 30, 36],  # dark: the white flat road and red/blue stand out
                ),
                rrb.Horizontal(
                    rrb.Spatial2DView(name="Residual legend", origin="legend"),
                    rrb.TextDocumentView(name="Summary", origin="summary"),
                    column_shares=[1, 2],
                ),
                row_shares=[4, 1],
            ),
            rrb.Vertical(
                rrb.Tabs(
                    rrb.MapView(name="Map", origin="map", zoom=zoom),
                    rrb.Spatial2DView(name="Mosaic", origin="mosaic"),
                    rrb.Spatial2DView(name="Surface residual", origin="surface"),
                    active_tab=0,
                ),
                rrb.Spatial2DView(name="Current frame", origin="world/camera"),
                rrb.Tabs(
                    rrb.TimeSeriesView(name="Per-frame", origin="frames"),
                    rrb.TextDocumentView(name="Frame", origin="frames/info"),
                    rrb.TextLogView(name="Warnings", origin="log"),
                    *profile_tabs,
                ),
                row_shares=[3, 3, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="frame", state="collapsed"),
    )
