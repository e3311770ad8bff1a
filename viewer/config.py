"""Viewer and run-report settings (frozen; loaded with ``roadsurf.core.config.from_dict``).

The viewer only reads a finished (or running) run folder; nothing here changes any result.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar


@dataclass(frozen=True)
class ViewerConfig:
    """How a run folder is turned into a Rerun recording and an HTML report."""

    max_cloud_points: int = (
        400_000  # points of the global cloud logged (random subset above), count
    )
    residual_range_percentile: float = (
        99.0  # |residual_m| percentile that saturates the colormap, %
    )
    min_residual_range_m: float = (
        0.005  # smallest colormap half-range (m), so flat roads stay white
    )
    colormap: str = "RdBu"  # matplotlib diverging colormap: red below the road, blue above
    defect_point_depth_m: float = (
        0.010  # 2D overlay marks matched points deeper than this (m), ~T_d
    )
    frame_stride: int = 1  # log every n-th frame on the timeline (images, overlays), count
    frustum_stride: int = 10  # static camera frusta drawn every n-th posed frame, count
    frustum_size_m: float = 0.25  # image-plane distance of the drawn frusta (m)
    max_mosaic_side_px: int = 2048  # mosaic / surface downscaled to at most this side (px)
    max_overlay_points: int = 3000  # matched / rejected features drawn per frame, count
    profile_samples: int = 64  # samples along each defect's long axis for its depth profile, count
    report_max_defects: int = 500  # rows in the report's defect table (sorted by severity), count

    # valid values (interval notation; see roadsurf.core.config)
    RANGES: ClassVar[dict[str, str]] = {
        "max_cloud_points": "[1, inf)",
        "residual_range_percentile": "(0, 100]",
        "min_residual_range_m": "(0, inf)",
        "defect_point_depth_m": "[0, 1]",
        "frame_stride": "[1, inf)",
        "frustum_stride": "[1, inf)",
        "frustum_size_m": "(0, inf)",
        "max_mosaic_side_px": "[16, inf)",
        "max_overlay_points": "[0, inf)",
        "profile_samples": "[2, inf)",
        "report_max_defects": "[0, inf)",
    }
