"""benchmarks.dense_pair_truth's ray cast against a known surface: a flat road with a square pit."""

from __future__ import annotations

import numpy as np

from benchmarks.dense_pair_truth import ray_cast


class _PitWorld:
    """z = 0, and -0.05 m inside |x|, |y| < 0.1 m; 'base' 0 everywhere (local metres)."""

    def evaluate(self, x0, y_top, gsd, rows, cols, appearance=False):  # noqa: ARG002
        xs = x0 + (np.arange(cols) + 0.5) * gsd
        ys = y_top - (np.arange(rows) + 0.5) * gsd
        X, Y = np.meshgrid(xs, ys)
        h = np.where((np.abs(X) < 0.1) & (np.abs(Y) < 0.1), -0.05, 0.0).astype(np.float32)
        return {"height": h, "base": np.zeros_like(h)}


def test_ray_cast_finds_the_floor_and_the_rim() -> None:
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking straight down
    T[:3, 3] = [0.0, 0.0, 0.5]
    rays = np.array([[0.0, 0.0, 1.0], [0.4, 0.0, 1.0], [0.15, 0.0, 1.0]])
    rng, res, slope = ray_cast(_PitWorld(), T, rays, 0.07, 0.13)
    # straight down into the pit; 0.2 m aside on the road; 0.075 m aside: the floor (x 0.082)
    assert abs(rng[0] - 0.55) < 1e-3
    assert abs(res[0] + 0.05) < 1e-6 and abs(res[1]) < 1e-6
    assert abs(rng[1] - 0.5 * np.sqrt(1 + 0.4**2)) < 1e-3
    assert abs(res[2] + 0.05) < 1e-6
    assert slope[0] < 1e-3
