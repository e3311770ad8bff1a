"""Defects (potholes, cracks, ruts) and depth-less distractors (lane markings, shadows, oil
stains) of the simulated road: each is a pure function of position (local metres)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roadsurf.simulation.noise import fractal_noise, value_noise
from roadsurf.simulation.shapes import Blob, Polyline, Rect

Window = tuple[float, float, float, float]  # x_min, y_min, x_max, y_max of a grid window (m)


@dataclass(frozen=True)
class Pothole:
    shape: Blob
    depth_m: float  # nominal depth D at the centre (m)
    power: float  # profile exponent: depth ∝ 1 - ρ^power (larger = flatter bottom, steeper wall)
    tilt: tuple[float, float]  # relative bottom tilt along x, y
    rough_m: float  # amplitude of the bottom roughness (m)
    darken: float  # albedo factor inside (< 1 darker)
    seed: int

    ragged: float = 0.05  # relative amplitude of the broken, ragged rim (fraction of ρ)

    def rho(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Normalised radius with a ragged rim: ρ (1 + ragged n(x, y)), n ~ clipped noise."""
        rho, _ = self.shape.rho_and_r(x, y)
        n = np.clip(value_noise(x, y, 0.02, self.seed + 17), -3.0, 3.0)
        return rho * (1.0 + self.ragged * n)

    def bbox(self, pad: float = 0.0) -> tuple[float, float, float, float]:
        return self.shape.bbox(pad + self.shape.r_max * (1.0 / (1.0 - 3 * self.ragged) - 1.0))

    def depth(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        rho = self.rho(x, y)
        prof = np.clip(1.0 - rho**self.power, 0.0, None)
        r = self.shape.radius
        lin = 1.0 + self.tilt[0] * (x - self.shape.cx) / r + self.tilt[1] * (y - self.shape.cy) / r
        rough = self.rough_m * fractal_noise(x, y, (0.015, 0.005), (1.0, 0.6), self.seed)
        d = self.depth_m * prof * lin + rough * np.sqrt(prof)
        return np.where(rho < 1.0, np.clip(d, 0.0, None), 0.0)


@dataclass(frozen=True)
class Trough:
    """A groove along a polyline: crack (narrow) or rut (wide, tapered ends)."""

    kind: str  # "crack" | "rut"
    line: Polyline
    depth_m: float  # depth at the centre line (m)
    taper_m: float  # length of the depth ramp at each end (m); 0 for cracks

    def depth(self, x: np.ndarray, y: np.ndarray, window: Window | None = None) -> np.ndarray:
        d, along = self.line.distance(x, y, window)
        q = np.clip(2.0 * d / self.line.width, 0.0, 1.0)
        if self.kind == "crack":
            prof = 1.0 - q**2
        else:
            prof = (1.0 - q**2) ** 2
        if self.taper_m > 0:
            L = self.line.length
            ramp = np.clip(np.minimum(along, L - along) / self.taper_m, 0.0, 1.0)
            prof = prof * ramp * ramp * (3 - 2 * ramp)
        return self.depth_m * prof

    def dist(self, x: np.ndarray, y: np.ndarray, window: Window | None = None) -> np.ndarray:
        return self.line.distance(x, y, window)[0]


@dataclass(frozen=True)
class Distractor:
    kind: str  # "lane_marking" | "shadow" | "oil_stain"
    shape: Blob | Rect
    strength: float  # paint coverage / shadow darkness / stain darkness (0..1)
    edge_m: float  # soft-edge width (m)
