"""The scenario space's figures: how many instances a perfect detector can pass, frames per instance.

A perfect detector finds the slow car in the first recorded frame at or after the lane change in which its
label is a Car/Van/Truck row (not DontCare: at least one cell of it visible). It passes when the gap at
that moment, the ego holding its closing speed of the lane change, still covers the stopping distance
(harness.sotif's rule). Labels only: no LiDAR scan, no image.

    python benchmarks/scenario_space.py [--instances 64] [--seed 0]
"""
from __future__ import annotations

import argparse

import numpy as np

from harness.core import kitti
from harness.core.braking import EGO_DIMS, stopping_distance
from simulator.dataset import GenerateConfig, plan_jobs
from simulator.frame import frame_state, world_scene
from simulator.labels import frame_labels
from simulator.lidar import LidarSpec
from simulator.scenario import window_length_s
from simulator.space import ScenarioSpace, instances


def perfect_detector(cfg: GenerateConfig, jobs: list) -> list[dict]:
    """Per instance: kinematic window (s), reveal delay after the lane change (s) and the verdict."""
    calib = kitti.kitti_calib(cfg.camera.width, cfg.camera.height)
    out = []
    for i, inst in enumerate(instances(cfg.space, cfg.seed)):
        mine = [j for j in jobs if j.instance == i]
        states = [frame_state(cfg, j) for j in mine]
        t_lc = states[0].info["lane_change_time_s"]
        after = [(j, s) for j, s in zip(mine, states) if s.time_s >= t_lc - 1e-9]
        s0 = after[0][1]
        gap0 = s0.info["slow_car_distance_m"] - (inst.sotif_config().slow_body[1][0] + EGO_DIMS[0]) / 2
        dv0 = s0.ego_speed - inst.slow_speed_kmh / 3.6
        seen = None
        for job, st in after:
            scene = world_scene(cfg, job)
            scene.set_vehicles(st.vehicles)
            labels, rows = frame_labels(scene, st.vehicles, st.pose, cfg.lidar.mount_height, calib, cfg.labels)
            row = rows[[v.role for v in st.vehicles].index("slow")]
            if row >= 0 and labels.name[row] != "DontCare":
                seen = st.time_s - s0.time_s
                break
        ok = seen is not None and gap0 - dv0 * seen >= stopping_distance(dv0)
        out.append({"window_s": window_length_s(gap0, dv0), "reveal_s": seen, "pass": ok, "frames": len(mine)})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--instances", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    cfg = GenerateConfig("sotif", 0, ("ClearNoon",), a.seed, LidarSpec(), space=ScenarioSpace(a.instances))
    jobs = plan_jobs(cfg)
    res = perfect_detector(cfg, jobs)
    frames = np.array([r["frames"] for r in res])
    reveal = np.array([r["reveal_s"] for r in res if r["reveal_s"] is not None])
    print(f"instances {len(res)} (seed {a.seed}); frames per instance min {frames.min()} median "
          f"{np.median(frames):.0f} mean {frames.mean():.1f} max {frames.max()}")
    print(f"kinematic pass (gap at the lane change >= stopping distance): "
          f"{np.mean([r['window_s'] > 0 for r in res]):.1%}")
    print(f"slow car first labelled {np.median(reveal):.1f} s after the lane change (median; "
          f"{len(res) - len(reveal)} never)")
    print(f"perfect detector passes: {np.mean([r['pass'] for r in res]):.1%}")


if __name__ == "__main__":
    main()
