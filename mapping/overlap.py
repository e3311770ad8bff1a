"""How much consecutive frames' road footprints overlap, and the warning when the map
becomes strips (below half, the two-view parts of consecutive pairs no longer touch)."""

from __future__ import annotations

import logging

import numpy as np

from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.types import MapProducts

log = logging.getLogger(__name__)


def consecutive_overlap(footprints_xy_m: list[np.ndarray]) -> np.ndarray:
    """(N-1,) share of frame i's road footprint that frame i+1 also sees (0-1; NaN where a
    footprint is missing). ``footprints_xy_m``: N arrays (K, 2) of footprint points (m), e.g.
    ``Camera.footprint_grid_enu``'s points; each footprint is their convex hull."""
    import shapely

    hulls = [
        shapely.MultiPoint(np.asarray(f, float)).convex_hull if len(f) >= 3 else None
        for f in footprints_xy_m
    ]
    out = np.full(max(0, len(hulls) - 1), np.nan)
    for i in range(len(out)):
        a, b = hulls[i], hulls[i + 1]
        if a is not None and b is not None and a.area > 0:
            out[i] = a.intersection(b).area / a.area
    return out


def check_frame_overlap(cfg: MappingConfig, fp_grid: list[np.ndarray], prod: MapProducts) -> None:
    """Record the consecutive-frame overlap and warn when it is below ``min_frame_overlap``:
    below half, the two-view parts of consecutive pairs no longer touch and the map is strips."""
    ov = consecutive_overlap(fp_grid)
    ov = ov[np.isfinite(ov)]
    if not len(ov):
        return
    med = float(np.median(ov))
    prod.frame_overlap = {"median": round(med, 3), "p10": round(float(np.percentile(ov, 10)), 3)}
    if med < cfg.min_frame_overlap:
        msg = (
            f"consecutive frames overlap by only {med:.0%} (median; below "
            f"{cfg.min_frame_overlap:.0%}): 3D comes from the overlaps, so the map is strips "
            "with unmeasured road between them, defects there are missed and long ones are "
            "measured in pieces. Drive slower or raise the frame rate (overlap = 1 - speed / "
            "(frame rate x footprint length along the drive))"
        )
        log.warning("globalmap: %s", msg)
        prod.warnings.append(msg)
