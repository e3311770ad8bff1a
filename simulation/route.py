"""The route's centreline and the camera's continuous motion along it.

Coordinates: local metric x (east), y (north), z (up), metres (see ``world``). Headings are grid
compass angles, clockwise from grid north (rad unless the name says deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Route:
    """Centreline sampled every ``ds`` metres of arc length; heading is grid compass (rad)."""

    s: np.ndarray  # (M,) arc length (m)
    xy: np.ndarray  # (M, 2) local x, y (m)
    heading: np.ndarray  # (M,) grid heading, clockwise from grid north (rad)

    @classmethod
    def make(
        cls, length_m: float, heading0: float, amp: float, wavelength: float, phase: float
    ) -> Route:
        ds = 0.05
        s = np.arange(0.0, length_m + ds, ds)
        hd = heading0 + amp * np.sin(2 * np.pi * s / wavelength + phase)
        dx = np.sin(hd) * ds
        dy = np.cos(hd) * ds
        xy = np.column_stack(
            [
                np.concatenate([[0.0], np.cumsum(0.5 * (dx[1:] + dx[:-1]))]),
                np.concatenate([[0.0], np.cumsum(0.5 * (dy[1:] + dy[:-1]))]),
            ]
        )
        return cls(s, xy, hd)

    def heading_at(self, s: np.ndarray) -> np.ndarray:
        return np.interp(s, self.s, self.heading)

    def point(self, s: np.ndarray, lateral: np.ndarray) -> np.ndarray:
        """(N, 2) local x, y of arc length ``s`` and lateral offset (m, + = right of travel)."""
        s = np.atleast_1d(np.asarray(s, float))
        lat = np.broadcast_to(np.asarray(lateral, float), s.shape)
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        h = self.heading_at(s)
        return np.column_stack([x + lat * np.cos(h), y - lat * np.sin(h)])


@dataclass
class Trajectory:
    """Camera motion sampled densely in time; poses are interpolated from it."""

    t: np.ndarray  # (T,) time (s)
    s: np.ndarray  # (T,) arc length along the route (m)
    speed: np.ndarray  # (T,) speed (m/s)
    lateral: np.ndarray  # (T,) lateral offset from the route centreline (m)
    dh: np.ndarray  # (T,) camera height deviation δ_h (m)
    roll: np.ndarray  # (T,) roll about camera y (rad)
    pitch: np.ndarray  # (T,) pitch about camera x (rad)
    yaw: np.ndarray  # (T,) yaw deviation from the road heading (rad)


@dataclass
class Pose:
    t: float
    C: np.ndarray  # (3,) camera centre, local x, y, z (m)
    R: np.ndarray  # (3, 3) world (grid E, N, U) from camera, the mount included
    heading_deg: float  # grid heading of the vehicle (deg)
    roll_rad: float  # vehicle roll (vibration), about the nadir camera's y (rad)
    pitch_rad: (
        float  # vehicle pitch (vibration + the road's slope), about the nadir camera's x (rad)
    )
