"""Coordinates of the detection map: the grid frame of the surface raster and exports.

With GPS the grid frame is the raster's projected CRS (the drive's UTM zone); points in the
local ENU frame are carried into it through WGS84, and outlines are exported as lon/lat.
Without GPS (``traj.reference is None``) the grid frame is the local ENU frame itself and no
lon/lat exist.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from pyproj import Transformer

from roadsurf.core.geometry import (
    EnuReference,
    ExportFrame,
    check_shape,
    enu_from_lla,
    lla_from_enu,
)


@dataclass(frozen=True)
class MapFrame:
    """Transforms between local ENU, the grid frame (``crs``) and WGS84 lon/lat."""

    reference: EnuReference | None  # None: no GPS, grid frame = local ENU
    crs: str  # CRS of the grid frame, e.g. "EPSG:32617"; "local ENU" without GPS

    @classmethod
    def create(cls, reference: EnuReference | None, raster_crs: str | None = None) -> MapFrame:
        if reference is None:
            return cls(None, "local ENU")
        crs = raster_crs or ExportFrame.for_reference(reference).crs
        return cls(reference, crs)

    @property
    def georeferenced(self) -> bool:
        return self.reference is not None

    @cached_property
    def _to_grid(self) -> Transformer:
        return Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)

    @cached_property
    def _to_lonlat(self) -> Transformer:
        return Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)

    def grid_from_enu(self, enu_m: np.ndarray) -> np.ndarray:
        """(N, 2|3) ENU metres -> (N, 2) grid-frame x, y (metres)."""
        enu = np.atleast_2d(np.asarray(enu_m, float))
        if enu.shape[1] == 2:
            enu = np.column_stack([enu, np.zeros(len(enu))])
        check_shape("enu_m", enu, (None, 3))
        if self.reference is None or len(enu) == 0:
            return enu[:, :2].copy()
        lla = lla_from_enu(enu, self.reference)
        x, y = self._to_grid.transform(lla[:, 1], lla[:, 0])
        return np.column_stack([np.asarray(x, float), np.asarray(y, float)])

    def enu_from_grid(self, xy_m: np.ndarray) -> np.ndarray:
        """(N, 2) grid-frame x, y (metres) -> (N, 2) local ENU east, north (metres) at the
        reference's height (the caller sets z: the road's ENU height where the point lies)."""
        xy = check_shape("xy_m", np.atleast_2d(np.asarray(xy_m, float)), (None, 2))
        if self.reference is None or len(xy) == 0:
            return xy.copy()
        ll = self.lonlat_from_grid(xy)
        return enu_from_lla(ll[:, 1], ll[:, 0], self.reference.alt_m, self.reference)[:, :2]

    def lonlat_from_grid(self, xy_m: np.ndarray) -> np.ndarray:
        """(N, 2) grid-frame metres -> (N, 2) lon, lat degrees. Raises without GPS."""
        if self.reference is None:
            raise ValueError("no GPS reference: lon/lat are not available (local frame only)")
        xy = check_shape("xy_m", np.atleast_2d(np.asarray(xy_m, float)), (None, 2))
        lon, lat = self._to_lonlat.transform(xy[:, 0], xy[:, 1])
        return np.column_stack([np.asarray(lon, float), np.asarray(lat, float)])
