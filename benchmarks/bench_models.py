"""Model-zoo benchmark: train (compact profile) -> export -> onnxruntime predictions -> KITTI AP.

Per model it prints and writes to ``<out>/bench_models.json``: training time, AP40 3D/BEV
(IoU 0.7) moderate and all-distance on held-out clear-weather frames of the training-scene
generator through onnxruntime, onnxruntime latency p50/p90, torch-eager latency on the same
frames, ONNX size and parameter count; with ``--sotif`` also the headline AP40 and the
30-50 / 50-80 m bins on the SOTIF ClearNoon frames.

    python -m benchmarks.bench_models --out /tmp/bench [--models pointpillars,second]
        [--train-data DIR] [--epochs N] [--heldout-frames 40] [--sotif] [--workers W]

Data sets are simulated once under ``<out>/data`` (or taken from ``--train-data``); training
resumes from / reuses ``<out>/runs/<model>/checkpoint.pt``.

``--speed`` trains nothing: per model (the trained ``<out>/runs/<model>/checkpoint.pt`` if there
is one, else random weights, which the output says) it prints onnxruntime, torch eager and
OpenVINO p50 on the same SOTIF frames (one thread each, CPU time of the process, so that other
work on the machine does not count), the GEMM GFLOP of a frame, the GEMM and
non-GEMM time from onnxruntime's profiler, and ORT time over the time the GEMMs would take at the
GEMM peak measured in the same run (a 2048^2 MatMul):

    python -m benchmarks.bench_models --speed --out /tmp/bench [--models ...] [--frames 10] [--data DIR]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from harness.core import kitti
from harness.core.files import atomic_write_text
from harness.dataset import KittiDataset

CLEAR = ("ClearNoon", "ClearSunset")


def simulate(out: Path, preset: str, frames: int | None, seed: int, weathers=None) -> Path:
    from simulator.dataset import generate

    if not (out / "meta" / "dataset.json").is_file():
        generate(out, preset=preset, frames=frames, seed=seed, weathers=weathers, progress=False)
    return out


def all_frames_split(root: Path, name: str = "bench_all") -> str:
    """A split file listing every frame of ``root`` (held-out data: no training frames)."""
    ids = sorted(p.stem for p in (root / "training" / "velodyne").glob("*.bin"))
    kitti.write_image_set(root / "ImageSets" / f"{name}.txt", ids)
    return name


def eager_latency(model, root: Path, split: str, frames: int) -> dict:
    """torch eager latency (ms) per frame, single thread, after one warm-up frame."""
    ds = KittiDataset(root, split)
    times = []
    with torch.no_grad():
        for i in range(min(frames, len(ds)) + 1):
            points = torch.from_numpy(ds[i % len(ds)].points)
            t0 = time.perf_counter()
            model(points)
            if i:
                times.append(1000 * (time.perf_counter() - t0))
    return {"p50": float(np.percentile(times, 50)), "p90": float(np.percentile(times, 90))}


def bench_model(name: str, args, train_root: Path, eval_root: Path, split: str) -> dict:
    from harness.evaluate import evaluate
    from harness.infer import predict
    from harness.train import default_workers, train
    from models.export import export_checkpoint
    from models.zoo import count_parameters, load_checkpoint

    run = args.out / "runs" / name
    t0 = time.perf_counter()
    workers = args.workers or default_workers(name, args.profile)  # data-parallel, one thread each
    ckpt = train(name, train_root, run, profile=args.profile, epochs=args.epochs.get(name), progress=True,
                 workers=workers)
    meta = torch.load(ckpt, map_location="cpu", weights_only=True)
    onnx_path = export_checkpoint(ckpt, args.out / "models" / f"{name}.onnx", expected_model=name)
    pred = predict(onnx_path, eval_root, args.out / "predictions" / name, split=split, progress=False, threads=1)
    res = evaluate(eval_root, args.out / "predictions" / name, split=eval_root / "ImageSets" / f"{split}.txt")
    model, _ = load_checkpoint(ckpt)
    eager = eager_latency(model, eval_root, split, args.latency_frames)
    row = {"model": name, "train_s": float(meta.get("train_seconds", time.perf_counter() - t0)),
           "workers": meta.get("workers", 1),
           "epochs": meta["epoch"],
           "ap3d_mod": res["kitti"]["3d"]["0.7"]["R40"]["moderate"],
           "apbev_mod": res["kitti"]["bev"]["0.7"]["R40"]["moderate"],
           "ap3d_all": res["headline"]["3d"]["0.7"], "apbev_all": res["headline"]["bev"]["0.7"],
           "ort_p50_ms": pred["latency_ms_p50"], "ort_p90_ms": pred["latency_ms_p90"],
           "torch_p50_ms": eager["p50"], "torch_p90_ms": eager["p90"],
           "onnx_mb": onnx_path.stat().st_size / 2 ** 20, "params": count_parameters(model)}
    if args.sotif:
        row.update(sotif_ap(name, onnx_path, args))
    return row


def sotif_ap(name: str, onnx_path: Path, args) -> dict:
    from harness.evaluate import evaluate
    from harness.infer import predict

    root = simulate(args.out / "data" / "sotif_clear", "sotif", None, 0, ["ClearNoon"])
    split = all_frames_split(root)
    predict(onnx_path, root, args.out / "predictions_sotif" / name, split=split, progress=False, threads=1)
    res = evaluate(root, args.out / "predictions_sotif" / name, split=root / "ImageSets" / f"{split}.txt")
    dist = res["distance"]["3d"]["0.7"]
    return {"sotif_ap3d_all": res["headline"]["3d"]["0.7"], "sotif_apbev_all": res["headline"]["bev"]["0.7"],
            "sotif_ap3d_30_50": dist.get("30-50"), "sotif_ap3d_50_80": dist.get("50-80")}


AP_COLS = [("model", "model", "{}"), ("train_s", "train s", "{:.0f}"), ("epochs", "epochs", "{}"),
           ("ap3d_mod", "AP40 3D mod", "{:.1f}"), ("apbev_mod", "AP40 BEV mod", "{:.1f}"),
           ("ap3d_all", "AP40 3D all", "{:.1f}"), ("ort_p50_ms", "ORT p50 ms", "{:.0f}"),
           ("ort_p90_ms", "ORT p90 ms", "{:.0f}"), ("torch_p50_ms", "torch p50 ms", "{:.0f}"),
           ("onnx_mb", "ONNX MB", "{:.1f}"), ("params", "params", "{:,}")]
SOTIF_COLS = [("sotif_ap3d_all", "SOTIF 3D all", "{:.1f}"), ("sotif_ap3d_30_50", "SOTIF 30-50", "{:.1f}"),
              ("sotif_ap3d_50_80", "SOTIF 50-80", "{:.1f}")]


def markdown(rows: list[dict], cols=None) -> str:
    if cols is None:
        cols = AP_COLS + (SOTIF_COLS if any("sotif_ap3d_all" in r for r in rows) else [])
    lines = ["| " + " | ".join(c[1] for c in cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = [fmt.format(r[k]) if r.get(k) is not None else "-" for k, _, fmt in cols]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


SPEED_COLS = [("model", "model", "{}"), ("weights", "weights", "{}"), ("ort_p50_ms", "ORT ms", "{:.0f}"),
              ("torch_p50_ms", "torch ms", "{:.0f}"), ("ov_p50_ms", "OpenVINO ms", "{:.0f}"),
              ("ov_same_boxes", "OV = ORT boxes", "{:.0%}"), ("gemm_gflop", "GEMM GFLOP", "{:.2f}"),
              ("gemm_ms", "GEMM ms", "{:.0f}"), ("other_ms", "non-GEMM ms", "{:.0f}"),
              ("ort_over_gemm_peak", "ORT / GEMM at peak", "{:.1f}"), ("top_other", "largest non-GEMM ops", "{}")]


def speed(args) -> list[dict]:
    """The ``--speed`` rows (see the module docstring)."""
    from benchmarks.model_speed import random_weights, speed_row
    from benchmarks.ort_profile import gemm_peak
    from models.export import export_checkpoint, export_onnx
    from models.zoo import build, load_checkpoint

    peak = gemm_peak()
    print(f"GEMM peak (onnxruntime MatMul 2048^2, one thread): {peak:.1f} GFLOP/s", flush=True)
    root = args.data or simulate(args.out / "data" / "sotif", "sotif", args.frames + 2, 0)
    ds = KittiDataset(root, all_frames_split(Path(root)), with_image=True)
    samples = [ds[i] for i in range(min(len(ds), args.frames + 2))]
    rows = []
    for name in args.models.split(","):
        ckpt, path = args.out / "runs" / name / "checkpoint.pt", args.out / "models" / f"{name}.onnx"
        if ckpt.is_file():
            model, _ = load_checkpoint(ckpt)
            export_checkpoint(ckpt, path, expected_model=name)
        else:
            torch.manual_seed(0)
            model = build(name, args.profile)
            random_weights(model, samples[-2:])
            export_onnx(model, path, {"sotif.profile": args.profile})
        row = {"model": name, "weights": "trained" if ckpt.is_file() else "random",
               **speed_row(model, path, samples[: args.frames], peak)}
        row["top_other"] = ", ".join(f"{op} {ms:.0f}" for op, ms in row["top_other"])
        rows.append(row)
        print(markdown(rows[-1:], SPEED_COLS), flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--models", default="pointpillars,second,dv_second")
    p.add_argument("--profile", default="compact")
    p.add_argument("--train-data", type=Path)
    p.add_argument("--epochs", default="", help="per model, e.g. pointpillars=2,second=1")
    p.add_argument("--heldout-frames", type=int, default=40)
    p.add_argument("--latency-frames", type=int, default=20)
    p.add_argument("--sotif", action="store_true")
    p.add_argument("--workers", type=int, help="data-parallel training processes (default: one per core, "
                                                "at most the batch size)")
    p.add_argument("--speed", action="store_true", help="runtime figures only (no training)")
    p.add_argument("--frames", type=int, default=10, help="--speed: SOTIF frames timed")
    p.add_argument("--data", type=Path, help="--speed: a data set to take the frames from (default: simulated)")
    args = p.parse_args(argv)
    args.epochs = {k: int(v) for k, v in (kv.split("=") for kv in args.epochs.split(",") if kv)}
    torch.set_num_threads(1)
    if args.speed:
        rows = speed(args)
        atomic_write_text(args.out / "bench_speed.json", json.dumps(rows, indent=1))
        print(markdown(rows, SPEED_COLS))
        return 0
    train_root = args.train_data or simulate(args.out / "data" / "train", "train", 400, 0)
    eval_root = simulate(args.out / "data" / "heldout_clear", "train", args.heldout_frames, 1, list(CLEAR))
    split = all_frames_split(eval_root)
    rows = []
    for name in args.models.split(","):
        rows.append(bench_model(name, args, Path(train_root), eval_root, split))
        print(markdown(rows[-1:]), flush=True)
    atomic_write_text(args.out / "bench_models.json", json.dumps(rows, indent=1))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
