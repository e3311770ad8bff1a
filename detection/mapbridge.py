"""Defects cut by an unknown strip (``detection.mapseg``): below 50 % frame overlap a strip
between two pairs' parts is seen by one frame and left unknown next to relief
(``MappingConfig.dense_single_view_relief_m``); the parts of a pothole it cuts are one defect.
Pure functions on (H, W) masks of the map's residual raster."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.cluster.hierarchy import DisjointSet


def bridged_components(
    rim: np.ndarray, rim_lab: np.ndarray, n_rim: int, unknown: np.ndarray, radius_px: float
) -> np.ndarray:
    """(n_rim + 1,) int: for each rim component (1..n_rim) of the (H, W) ``rim`` mask, a group
    number shared by the parts of one defect cut by an unknown strip: ``rim`` is closed (a disk
    of ``radius_px``) through ``unknown`` cells only, and two components that one piece of that
    bridge touches are joined when each touches it along at least half its own equivalent side
    (√cells / 2): a pothole cut across meets the strip along its width on both sides, a second
    pothole that only grazes the strip with a corner stays apart. Index 0 and components not
    joined keep their own number."""
    out = np.arange(n_rim + 1)
    if radius_px <= 0 or n_rim < 2 or not unknown.any():
        return out
    # closing by a disk through distance transforms: dilate (within r of rim), then erode
    grown = ndimage.distance_transform_edt(~rim) <= radius_px
    closed = ndimage.distance_transform_edt(grown) > radius_px
    bridge = closed & unknown & ~rim
    if not bridge.any():
        return out
    blab, _ = ndimage.label(bridge, structure=np.ones((3, 3), bool))
    near = ndimage.grey_dilation(blab, size=3)  # a bridge piece's label on the cells around it
    touch = rim & (near > 0)
    if not touch.any():
        return out
    size = np.bincount(rim_lab[rim], minlength=n_rim + 1)
    key = rim_lab[touch].astype(np.int64) * (int(blab.max()) + 1) + near[touch]
    keys, contact = np.unique(key, return_counts=True)
    comp, piece = np.divmod(keys, int(blab.max()) + 1)
    ok = contact >= 0.5 * np.sqrt(size[comp])
    sets = DisjointSet(range(n_rim + 1))
    first: dict[int, int] = {}
    for c, p in zip(comp[ok].tolist(), piece[ok].tolist(), strict=True):
        sets.merge(c, first.setdefault(p, c))
    return np.array([sets[i] for i in range(n_rim + 1)])
