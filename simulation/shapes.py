"""Planar shapes the world is made of (local metric x east, y north, metres), evaluated on grids.

- ``Blob``: star-shaped irregular outline r(φ) = R (1 + Σ a_k cos(kφ + φ_k)); potholes, oil
  stains and shadow blobs. ``rho`` is the normalised radius (1 on the outline).
- ``Rect``: oriented rectangle; lane-marking dashes and pole shadows.
- ``Polyline``: a path with a width; cracks and ruts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Blob:
    cx: float  # centre x (m)
    cy: float  # centre y (m)
    radius: float  # mean radius R (m)
    amps: tuple[float, ...]  # harmonic amplitudes a_k for k = 2, 3, ... (fractions of R)
    phases: tuple[float, ...]  # harmonic phases φ_k (rad)

    def r_of_phi(self, phi: np.ndarray) -> np.ndarray:
        r = np.ones_like(phi)
        for k, (a, p) in enumerate(zip(self.amps, self.phases, strict=True), start=2):
            r = r + a * np.cos(k * phi + p)
        return self.radius * r

    @property
    def r_max(self) -> float:
        return self.radius * (1.0 + float(np.sum(np.abs(self.amps))))

    def bbox(self, pad: float = 0.0) -> tuple[float, float, float, float]:
        r = self.r_max + pad
        return (self.cx - r, self.cy - r, self.cx + r, self.cy + r)

    def rho_and_r(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised radius ρ = d / r(φ) and the outline radius r(φ) at each point."""
        dx, dy = x - self.cx, y - self.cy
        r = self.r_of_phi(np.arctan2(dy, dx))
        return np.hypot(dx, dy) / r, r

    def outline(self, n: int = 96) -> np.ndarray:
        """(n, 2) points on the outline ρ = 1, counter-clockwise."""
        phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
        r = self.r_of_phi(phi)
        return np.column_stack([self.cx + r * np.cos(phi), self.cy + r * np.sin(phi)])

    def soft_mask(self, x: np.ndarray, y: np.ndarray, edge_m: float) -> np.ndarray:
        """1 inside, 0 outside, linear ramp of width ``edge_m`` centred on the outline."""
        rho, r = self.rho_and_r(x, y)
        return np.clip(0.5 - (rho - 1.0) * r / max(edge_m, 1e-6), 0.0, 1.0)


@dataclass(frozen=True)
class Rect:
    cx: float  # centre x (m)
    cy: float  # centre y (m)
    angle: float  # direction of the long axis, radians counter-clockwise from +x (east)
    length: float  # along the long axis (m)
    width: float  # across (m)

    def local(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(self.angle), np.sin(self.angle)
        dx, dy = x - self.cx, y - self.cy
        return dx * c + dy * s, -dx * s + dy * c

    def bbox(self, pad: float = 0.0) -> tuple[float, float, float, float]:
        p = self.outline()
        return (p[:, 0].min() - pad, p[:, 1].min() - pad, p[:, 0].max() + pad, p[:, 1].max() + pad)

    def outline(self) -> np.ndarray:
        c, s = np.cos(self.angle), np.sin(self.angle)
        u = np.array([-1, 1, 1, -1]) * self.length / 2
        v = np.array([-1, -1, 1, 1]) * self.width / 2
        return np.column_stack([self.cx + u * c - v * s, self.cy + u * s + v * c])

    def soft_mask(self, x: np.ndarray, y: np.ndarray, edge_m: float) -> np.ndarray:
        u, v = self.local(x, y)
        sd = np.maximum(np.abs(u) - self.length / 2, np.abs(v) - self.width / 2)
        return np.clip(0.5 - sd / max(edge_m, 1e-6), 0.0, 1.0)


@dataclass(frozen=True)
class Polyline:
    points: tuple[tuple[float, float], ...]  # vertices (m)
    width: float  # full width (m)

    @property
    def array(self) -> np.ndarray:
        return np.asarray(self.points, dtype=np.float64)

    @property
    def length(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.array, axis=0), axis=1)))

    def bbox(self, pad: float = 0.0) -> tuple[float, float, float, float]:
        p = self.array
        h = self.width / 2 + pad
        return (p[:, 0].min() - h, p[:, 1].min() - h, p[:, 0].max() + h, p[:, 1].max() + h)

    def distance(
        self, x: np.ndarray, y: np.ndarray, window: tuple[float, float, float, float] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance to the polyline (m) and the arc length of the closest point (m).

        ``window`` (xmin, ymin, xmax, ymax) skips segments that cannot be within width of it.
        """
        p = self.array
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        best = np.full(np.shape(x), np.inf, dtype=np.float64)
        along = np.zeros(np.shape(x), dtype=np.float64)
        h = self.width
        for i in range(len(p) - 1):
            a, b = p[i], p[i + 1]
            if window is not None:
                if (
                    max(a[0], b[0]) < window[0] - h
                    or min(a[0], b[0]) > window[2] + h
                    or max(a[1], b[1]) < window[1] - h
                    or min(a[1], b[1]) > window[3] + h
                ):
                    continue
            d = b - a
            ll = float(d @ d)
            t = np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / max(ll, 1e-12), 0.0, 1.0)
            dist = np.hypot(x - (a[0] + t * d[0]), y - (a[1] + t * d[1]))
            m = dist < best
            best = np.where(m, dist, best)
            along = np.where(m, cum[i] + t * np.sqrt(ll), along)
        return best, along
