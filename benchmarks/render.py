"""Benchmark: the simulator's render time per frame, with a breakdown, on this machine.

``make bench-render ARGS="--scenario sample --frames 20"`` (was ``roadsurf bench render``)
renders in memory (no files) and writes ``benchmarks/results/render.json``.
"""

from __future__ import annotations

import resource
import time
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.simulation.build import build_world
from roadsurf.simulation.render import Renderer
from roadsurf.simulation.scenarios import SCENARIOS, make_config
from roadsurf.simulation.sensors import encode_image, form_image


def bench_render(
    scenario: str = "sample", n_frames: int = 20, **overrides: Any
) -> dict[str, float | int | str]:
    """Render ``n_frames`` of ``scenario`` in memory (no files) and time each step.

    Returns wall-clock seconds per frame (and the process CPU time, all threads, which is less
    sensitive to other jobs on a shared machine): total, world tiles (evaluating the height field and appearance),
    ray casting (the rest of ``Renderer.render``), sensor model and image encoding; plus the
    world build time, the tile cache size and the process's peak RSS.
    """
    cfg = make_config(scenario, **overrides)
    seed = SCENARIOS[scenario].seed
    t0 = time.perf_counter()
    world = build_world(cfg, seed, n_frames)
    t_build = time.perf_counter() - t0
    r = Renderer(world)
    times = {"render": [], "sensor": [], "encode": []}
    rng = np.random.default_rng(0)
    tiles_before = 0.0
    tile_per_frame = []
    cpu = []
    for k in range(n_frames):
        c0 = time.process_time()
        pose = world.pose(float(world.frame_times[k]))
        t1 = time.perf_counter()
        fr = r.render(pose)
        t2 = time.perf_counter()
        img = form_image(fr.radiance, cfg, cfg.speed_mps, 1.0, rng)
        t3 = time.perf_counter()
        encode_image(img, cfg)
        t4 = time.perf_counter()
        times["render"].append(t2 - t1)
        times["sensor"].append(t3 - t2)
        times["encode"].append(t4 - t3)
        cpu.append(time.process_time() - c0)
        tile_per_frame.append(r.tile_seconds - tiles_before)
        tiles_before = r.tile_seconds
    # Skip the first frame (it builds the whole first mosaic and warms caches).
    sl = slice(1, None) if n_frames > 1 else slice(None)
    render = np.array(times["render"])[sl]
    tiles = np.array(tile_per_frame)[sl]
    sensor = np.array(times["sensor"])[sl]
    encode = np.array(times["encode"])[sl]
    total = render + sensor + encode
    tile_mb = r.tile * r.tile * 5 * 4 / 1e6
    return {
        "scenario": scenario,
        "frames": n_frames,
        "image": f"{cfg.width}x{cfg.height}",
        "supersample": cfg.supersample,
        "render_gsd_mm": world.render_gsd_m * 1000,
        "world_build_s": t_build,
        "s_per_frame_median": float(np.median(total)),
        "s_per_frame_mean": float(np.mean(total)),
        "cpu_s_per_frame_median": float(np.median(np.array(cpu)[sl])),
        "tiles_s_per_frame": float(np.median(tiles)),
        "raycast_s_per_frame": float(np.median(render - tiles)),
        "sensor_s_per_frame": float(np.median(sensor)),
        "encode_s_per_frame": float(np.median(encode)),
        "tiles_made": r.tiles_made,
        "tile_cache_mb": len(r.cache) * tile_mb,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.render [--scenario S] [--frames N] [--width W] [--height H]``."""
    import argparse

    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(
        description="Simulator render time per frame (world tiles, ray casting, sensor, encoding)."
    )
    ap.add_argument("--scenario", default="sample", help="scenario to render")
    ap.add_argument("--frames", type=int, default=20, help="frames to render (in memory)")
    ap.add_argument("--width", type=int, default=640, help="image width (px)")
    ap.add_argument("--height", type=int, default=480, help="image height (px)")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    fx = 600.0 * a.width / 640.0  # the focal length scales with the width (600 px at 640)
    res = bench_render(a.scenario, a.frames, width=a.width, height=a.height, fx=fx)
    for k, v in res.items():
        print(f"{k:22s} {v:.3f}" if isinstance(v, float) else f"{k:22s} {v}")
    write_result(a.json, "render", res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
