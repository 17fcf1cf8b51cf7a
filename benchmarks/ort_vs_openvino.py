"""onnxruntime against OpenVINO on the same frames, paired: which runtime is faster for a model.

Two separate probes of the same file rank the two runtimes differently (both move up to 25 %
between runs on a shared machine). Here every frame runs in the order onnxruntime, OpenVINO,
OpenVINO, onnxruntime (ABBA), so that drift of the machine falls on both alike; per frame the
ratio of OpenVINO's mean time to onnxruntime's, and over frames its median with a bootstrap 95 %
interval. A ratio below 1 with the interval below 1: OpenVINO is faster for that model.

    python -m benchmarks.ort_vs_openvino RUN_DIR [--frames 20] [--models a,b] [--threads 2]

Frames: the first ``--frames`` of the run's SOTIF test split (``RUN/data/sotif``), as the run's
runtime probe takes them.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from harness.infer import OnnxDetector, frame_inputs
from harness.runtime import first_test_frames

MODELS = "pointpillars,second,dv_second,parta2,pv_rcnn,point_rcnn,mvx_net"


def paired_ratio(first: np.ndarray, second: np.ndarray, seed: int = 0, draws: int = 1000) -> tuple[float, float, float]:
    """Median over frames of second / first per frame, and its bootstrap 95 % interval."""
    ratio = np.asarray(second) / np.asarray(first)
    rng = np.random.default_rng(seed)
    boot = [np.median(rng.choice(ratio, len(ratio))) for _ in range(draws)]
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return float(np.median(ratio)), float(lo), float(hi)


def frame_feeds(det: OnnxDetector, data: Path, fid: str) -> tuple:
    """points, image, lidar2img of a frame as the detector takes them (image None for LiDAR models)."""
    points, _, image, lidar2img, _ = frame_inputs(det, data, fid)
    return points, image, lidar2img


def time_pair(ort_det, ov_det, inputs) -> tuple[np.ndarray, np.ndarray]:
    """Per frame the mean of two onnxruntime and two OpenVINO runs (ABBA order), ms."""
    ort_ms, ov_ms = [], []
    for x in inputs:
        t = []
        for det in (ort_det, ov_det, ov_det, ort_det):
            t0 = time.perf_counter()
            det(*x)
            t.append(1000.0 * (time.perf_counter() - t0))
        ort_ms.append((t[0] + t[3]) / 2)
        ov_ms.append((t[1] + t[2]) / 2)
    return np.array(ort_ms), np.array(ov_ms)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--models", default=MODELS)
    p.add_argument("--threads", type=int, default=2, help="onnxruntime's threads (OpenVINO takes the cores)")
    args = p.parse_args(argv)
    data = args.run / "data" / "sotif"
    ids = first_test_frames(data, args.frames)
    print(f"{len(ids)} SOTIF frames, onnxruntime {args.threads} threads, ABBA per frame")
    print("| model | ORT p50 ms | OpenVINO p50 ms | OpenVINO / ORT per frame, median [95 %] | faster |")
    print("|---|---|---|---|---|")
    for name in args.models.split(","):
        path = args.run / "models" / f"{name}.onnx"
        ort_det = OnnxDetector(path, "onnxruntime", threads=args.threads)
        ov_det = OnnxDetector(path, "openvino")
        inputs = [frame_feeds(ort_det, data, fid) for fid in ids]
        for det in (ort_det, ov_det):
            det(*inputs[0])  # warm-up
        ort_ms, ov_ms = time_pair(ort_det, ov_det, inputs)
        med, lo, hi = paired_ratio(ort_ms, ov_ms)
        faster = "OpenVINO" if hi < 1 else "onnxruntime" if lo > 1 else "tie"
        print(f"| {name} | {np.median(ort_ms):.1f} | {np.median(ov_ms):.1f} | {med:.3f} [{lo:.3f}, {hi:.3f}] | {faster} |",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
