"""Time the KITTI evaluator on a generated KITTI-val-sized set (3,769 frames, ~8 objects and
~30 detections each): all four metrics, overlaps 0.7 / 0.5 / official 0.5, AP11 and AP40.

    python benchmarks/bench_eval.py [--frames 3769]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from harness.core.kitti import Labels, kitti_calib
from harness.eval_kitti import build_eval_set, kitti_ap


def generated_frames(n_frames: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    calib = kitti_calib()
    gts, dts = [], []
    for _ in range(n_frames):
        k = rng.poisson(8)
        boxes = np.c_[rng.uniform(5, 70, k), rng.uniform(-15, 15, k), np.full(k, -0.9), rng.uniform(3.5, 4.8, k),
                      rng.uniform(1.5, 1.9, k), rng.uniform(1.3, 1.8, k), rng.uniform(-np.pi, np.pi, k)]
        names = rng.choice(["Car"] * 7 + ["Van", "DontCare"], k)
        gt = Labels.from_lidar(boxes, calib, names, truncated=rng.choice([0, 0.2, 0.4], k),
                               occluded=rng.integers(0, 3, k))
        m = rng.poisson(30)
        src = rng.integers(0, max(k, 1), m)
        real = (rng.uniform(size=m) < 0.25) & (k > 0)
        det = np.c_[rng.uniform(5, 70, m), rng.uniform(-15, 15, m), np.full(m, -0.9), rng.uniform(3.5, 4.8, m),
                    rng.uniform(1.5, 1.9, m), rng.uniform(1.3, 1.8, m), rng.uniform(-np.pi, np.pi, m)]
        if k:
            det[real] = boxes[src[real]] + rng.normal(0, 0.15, (real.sum(), 7)) * [1, 1, 0.3, 0.3, 0.1, 0.1, 0.3]
        gts.append(gt)
        dts.append(Labels.from_lidar(det, calib, ["Car"] * m, score=rng.uniform(size=m)))
    return gts, dts


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=3769)
    n = ap.parse_args().frames
    gts, dts = generated_frames(n)
    kitti_ap(build_eval_set(gts[:20], dts[:20]))  # compile (numba caches on disk after the first run)
    t0 = time.perf_counter()
    es = build_eval_set(gts, dts)
    t1 = time.perf_counter()
    res = kitti_ap(es)
    t2 = time.perf_counter()
    n_gt = sum(len(g) for g in gts)
    n_dt = sum(len(d) for d in dts)
    print(f"frames {n}, objects {n_gt} ({n_gt / n:.1f}/frame), detections {n_dt} ({n_dt / n:.1f}/frame)")
    print(f"overlaps (bbox, BEV, 3D): {t1 - t0:.2f} s; AP for 4 metrics x 3 overlap sets x AP11/AP40 x 3 "
          f"difficulties: {t2 - t1:.2f} s; total {t2 - t0:.2f} s")
    print(f"3D AP40 @0.7 moderate {res['3d']['0.7']['R40']['moderate']:.2f}, "
          f"BEV {res['bev']['0.7']['R40']['moderate']:.2f}, bbox {res['bbox']['0.7']['R40']['moderate']:.2f}")


if __name__ == "__main__":
    main()
