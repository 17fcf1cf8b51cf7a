"""Benchmark of the two-stage voxel detectors (Part-A2, PV-RCNN) in the compact profile.

Per model: train on ``<data>/ImageSets/train.txt`` (or reuse a checkpoint of an earlier run),
export to ONNX (unless the file is newer than the checkpoint), run onnxruntime over the ``val`` split, evaluate (KITTI AP40 3D moderate,
headline AP40, Recall at RoI / RCNN at 0.3 / 0.5 / 0.7 on ClearNoon-like clear frames and on
all frames), torch-eager vs onnxruntime latency on the same frames, file size, parameters.

    python benchmarks/bench_two_stage.py --data DIR --out DIR [--models parta2,pv_rcnn]
        [--epochs 1] [--frames 20]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

import numpy as np

from harness.core.files import atomic_write_text
from harness.core.kitti import read_frames_meta, write_image_set
from harness.dataset import KittiDataset
from harness.evaluate import evaluate
from harness.infer import OnnxDetector, predict
from harness.runtime import outputs_agree
from harness.train import train
from models.export import export_checkpoint
from models.zoo import count_parameters, load_checkpoint

CLEAR = ("ClearNoon", "ClearSunset", "ClearNight")  # the dry, clear-sky presets


def clear_split(data: Path, split: str, out: Path) -> Path | None:
    """ImageSets-style file with the frames of ``split`` under a clear preset (None if none)."""
    meta = read_frames_meta(data / "meta" / "frames.csv")
    ids = meta[(meta["split"] == split) & meta["weather"].isin(CLEAR)]["frame_id"].tolist()
    if not ids:
        return None
    path = out / f"{split}_clear.txt"
    write_image_set(path, ids)
    return path


def summarise(result: dict) -> dict:
    k = result["kitti"]
    rec = result["recall"]
    return {"ap40_3d_moderate": k["3d"]["0.7"]["R40"]["moderate"],
            "ap40_bev_moderate": k["bev"]["0.7"]["R40"]["moderate"],
            "ap40_3d_headline": result["headline"]["3d"]["0.7"],
            "recall_roi": rec.get("roi"), "recall_rcnn": rec.get("rcnn"), "frames": result["n_frames"]}


def eager_vs_ort(ckpt: Path, onnx_path: Path, data: Path, n_frames: int) -> dict:
    """torch eager vs onnxruntime (one thread each) on the first val frames: p50 latencies,
    speed ratio and output agreement (same boxes, largest score difference)."""
    model, _ = load_checkpoint(ckpt)
    det = OnnxDetector(onnx_path, threads=1)
    ds = KittiDataset(data, "val")
    t_torch, t_ort, same, diffs = [], [], [], []
    for i in range(min(n_frames, len(ds))):
        points = ds[i].points
        with torch.no_grad():
            model(torch.from_numpy(points))  # warm-up
            t0 = time.perf_counter()
            out_t = model(torch.from_numpy(points))
            t_torch.append(1000 * (time.perf_counter() - t0))
        det(points, None, None)
        t0 = time.perf_counter()
        out_o = det(points, None, None)
        t_ort.append(1000 * (time.perf_counter() - t0))
        ok, d, _ = outputs_agree({"boxes": out_t[0].numpy(), "scores": out_t[1].numpy()}, out_o)
        same.append(ok)
        diffs += [] if np.isnan(d) else [d]
    p50_t, p50_o = float(np.median(t_torch)), float(np.median(t_ort))
    return {"torch_eager_ms_p50": p50_t, "ort_ms_p50_same_frames": p50_o, "ort_speedup": p50_t / p50_o,
            "agreement": {"same_boxes": float(np.mean(same)), "frames": len(same),
                          "max_abs_score_diff": max(diffs) if diffs else None}}


def bench_model(name: str, data: Path, out: Path, epochs: int, frames: int) -> dict:
    torch.set_num_threads(1)
    run = out / name
    t0 = time.perf_counter()
    ckpt = train(name, data, run, profile="compact", epochs=epochs, progress=True)
    meta = torch.load(ckpt, map_location="cpu", weights_only=True)
    onnx_path = run / f"{name}.onnx"
    if not onnx_path.is_file() or onnx_path.stat().st_mtime < ckpt.stat().st_mtime:
        export_checkpoint(ckpt, onnx_path, expected_model=name)
    preds = run / "predictions"
    lat = predict(onnx_path, data, preds, split="val", progress=True, threads=1)
    row = {"model": name, "train_seconds": meta.get("train_seconds"), "epochs": meta.get("epochs"),
           "wall_seconds_total": None, "ort_ms_p50": lat["latency_ms_p50"],
           "ort_ms_p90": lat["latency_ms_p90"], "onnx_mb": onnx_path.stat().st_size / 2 ** 20,
           "parameters": count_parameters(load_checkpoint(ckpt)[0])}
    row["all"] = summarise(evaluate(data, preds, split=data / "ImageSets" / "val.txt"))
    clear = clear_split(data, "val", run)
    row["clear"] = summarise(evaluate(data, preds, split=clear)) if clear else None
    cmp = eager_vs_ort(ckpt, onnx_path, data, frames)
    row["torch_eager_ms_p50"] = cmp["torch_eager_ms_p50"]
    row["ort_speedup"] = cmp["ort_speedup"]
    row["agreement"] = cmp["agreement"]
    row["wall_seconds_total"] = time.perf_counter() - t0
    return row


def table(rows: list[dict]) -> str:
    lines = ["| model | train s | AP40 3D mod. (clear) | AP40 3D mod. (all val) | Recall RoI @0.3/0.5 "
             "| Recall RCNN @0.3/0.5 | ORT p50/p90 ms | eager / ORT | MB | params |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c = r["clear"] or r["all"]
        roi, rcnn = r["all"]["recall_roi"] or {}, r["all"]["recall_rcnn"] or {}
        lines.append(
            f"| {r['model']} | {r['train_seconds']:.0f} | {c['ap40_3d_moderate']:.2f} | "
            f"{r['all']['ap40_3d_moderate']:.2f} | {100 * roi.get('0.3', float('nan')):.1f} / "
            f"{100 * roi.get('0.5', float('nan')):.1f} | {100 * rcnn.get('0.3', float('nan')):.1f} / "
            f"{100 * rcnn.get('0.5', float('nan')):.1f} | {r['ort_ms_p50']:.0f} / {r['ort_ms_p90']:.0f} | "
            f"{r['ort_speedup']:.2f} | {r['onnx_mb']:.1f} | {r['parameters']:,} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--models", default="parta2,pv_rcnn")
    ap.add_argument("--epochs", type=int, default=1)
    ap.add_argument("--frames", type=int, default=20, help="frames of the torch-vs-ORT comparison")
    args = ap.parse_args()
    rows = [bench_model(m, args.data, args.out, args.epochs, args.frames) for m in args.models.split(",")]
    atomic_write_text(args.out / "bench_two_stage.json", json.dumps(rows, indent=1))
    text = table(rows)
    atomic_write_text(args.out / "bench_two_stage.md", text + "\n")
    print(text)


if __name__ == "__main__":
    main()
