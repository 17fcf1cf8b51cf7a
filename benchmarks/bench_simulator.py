"""Simulator speed: LiDAR rays/s (with weather) against raw Embree on the same scene,
frames/s of the full frame pipeline, and the time to generate the SOTIF set on 2 workers.

    python benchmarks/bench_simulator.py [--repeats 10] [--frames 20] [--workers 2]
        [--weathers ClearNoon,HardRainNight] [--only rays,frames,full] [--default-malloc]
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from simulator import generate
from simulator.dataset import GenerateConfig, plan_jobs, run_job, worker_init
from simulator.lidar import LidarSpec, ray_directions, scan
from simulator.raycast import RayScene
from simulator.road import RoadConfig
from simulator.scenario import sotif_run
from simulator.weather import WEATHER_PRESETS
from simulator.world import build_world


def bench_rays(repeats: int, weathers: list[str]) -> None:
    """Median wall and CPU time per scan: raw embreex on one merged BVH against scan() per weather."""
    road = RoadConfig()
    scene = RayScene(build_world(road, np.random.default_rng(0)))
    state = sotif_run(road, 27, np.random.default_rng(0))[10]
    scene.set_vehicles(state.vehicles)
    spec = LidarSpec()
    dirs = ray_directions(spec) @ state.pose.rotation().T
    n = len(dirs)
    merged = rtcs.EmbreeScene()  # one BVH over the world and the vehicles: the raw reference
    TriangleMesh(merged, np.concatenate([scene.world.triangles] + [t.astype(np.float32) for t in scene.vehicle_triangles]))
    origins = np.tile(np.array([state.pose.x, state.pose.y, spec.mount_height], np.float32), (n, 1))
    dirs32 = np.ascontiguousarray(dirs, dtype=np.float32)
    runs = {"raw": lambda: merged.run(origins, dirs32, output=1),
            "raw, hits up to max_range": lambda: merged.run(origins, dirs32, dists=spec.max_range, output=1)}
    for name in weathers:
        rng = np.random.default_rng(1)
        runs[name] = lambda w=WEATHER_PRESETS[name], rng=rng: scan(scene, spec, state.pose, w, state.vehicles, rng)
    print(f"rays per scan: {n} ({len(spec.elevations_deg)} channels x {spec.n_azimuth} azimuths), "
          f"median of {repeats}, load average {_load()}")
    samples = {name: ([], []) for name in runs}
    for name, fn in runs.items():
        fn()
    for _ in range(repeats):  # interleaved rounds, so that load changes hit every variant alike
        for name, fn in runs.items():
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            samples[name][0].append(time.perf_counter() - w0)
            samples[name][1].append(time.process_time() - c0)
    wall = {name: float(np.median(w)) for name, (w, _) in samples.items()}
    cpu = {name: float(np.median(c)) for name, (_, c) in samples.items()}
    for name in runs:
        print(f"  {name:28s} {n / wall[name] / 1e6:5.2f} M rays/s ({wall[name] * 1e3:5.1f} ms wall, "
              f"{cpu[name] * 1e3:5.1f} ms CPU) = {100 * cpu['raw'] / cpu[name]:3.0f} % of raw rays/s by CPU time, "
              f"{100 * wall['raw'] / wall[name]:3.0f} % by wall time")


def bench_frames(frames: int) -> None:
    cfg = GenerateConfig("sotif", 547, tuple(WEATHER_PRESETS), 0, LidarSpec())
    jobs = plan_jobs(cfg)[:: max(1, 547 // frames)][:frames]
    root = Path(tempfile.mkdtemp(prefix="bench_sim_"))
    try:
        (root / "meta" / "frames").mkdir(parents=True)
        run_job((root, cfg, jobs[0], cfg.digest()))  # world build, caches
        t0, c0 = time.perf_counter(), time.process_time()
        for job in jobs[1:]:
            run_job((root, cfg, job, cfg.digest()))
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        shutil.rmtree(root)
    n = len(jobs) - 1
    print(f"frames/s, one process (scan + image + labels + files): {n / dt:.2f} ({1e3 * dt / n:.0f} ms/frame wall, "
          f"{1e3 * cpu / n:.0f} ms/frame CPU -> {547 * cpu / n / 2:.0f} s for 547 frames on 2 idle cores)")


def _cpu_seconds() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def bench_full(workers: int) -> None:
    root = Path(tempfile.mkdtemp(prefix="bench_sotif_"))
    try:
        t0, c0 = time.perf_counter(), _cpu_seconds()
        generate(root / "sotif", "sotif", workers=workers, progress=False)
        dt, cpu = time.perf_counter() - t0, _cpu_seconds() - c0
    finally:
        shutil.rmtree(root)
    print(f"full SOTIF set (547 frames, LiDAR + 1242x375 images + labels) on {workers} workers: {dt:.1f} s wall, "
          f"{cpu:.1f} CPU s (= {cpu / workers:.1f} s on {workers} otherwise idle cores); "
          f"load average at the end: {_load()}")


def _load() -> str:
    return "{:.1f}".format(os.getloadavg()[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--weathers", default="ClearNoon,HardRainNight",
                    help="comma-separated presets for the rays/s comparison")
    ap.add_argument("--only", default="rays,frames,full", help="comma-separated parts: rays, frames, full")
    ap.add_argument("--default-malloc", action="store_true",
                    help="keep glibc's malloc settings (the generator's workers use simulator.dataset.worker_init)")
    args = ap.parse_args()
    weathers = [w for w in args.weathers.split(",") if w]
    bad = [w for w in weathers if w not in WEATHER_PRESETS]
    parts = set(args.only.split(","))
    if bad or not parts <= {"rays", "frames", "full"}:
        ap.error(f"unknown weather(s) {bad} or part(s) {sorted(parts - {'rays', 'frames', 'full'})}")
    print(f"load average (1 min) at start: {_load()} on {os.cpu_count()} cores")
    if not args.default_malloc:
        worker_init()
    if "rays" in parts:
        bench_rays(args.repeats, weathers)
    if "frames" in parts:
        bench_frames(args.frames)
    if "full" in parts:
        bench_full(args.workers)


if __name__ == "__main__":
    main()
