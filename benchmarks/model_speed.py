"""Speed of one exported detector on the same frames in onnxruntime, torch eager and OpenVINO
(one thread each), its GEMM time and FLOPs (``benchmarks/ort_profile.py``), the rest of its
latency (non-GEMM), and
how far it runs from this CPU's GEMM peak. Used by ``bench_models.py --speed``.

Without a trained checkpoint the models get random weights that behave like trained ones where
it matters for speed: BatchNorm statistics from two frames and class layers scaled so that scores
spread over (0, 1) (a fresh head scores every anchor ~0.01 and no box reaches the NMS).
"""
from __future__ import annotations

import time

import numpy as np
import torch

from benchmarks.ort_profile import profile_frames, session
from harness.runtime import outputs_agree
from models.base import reset_norm_statistics


def frame_inputs(model, sample) -> list[np.ndarray]:
    """The graph inputs of one frame: points, and image + lidar2img for camera models."""
    inputs = [np.ascontiguousarray(sample.points, np.float32)]
    if model.uses_camera:
        inputs += [sample.image[None].astype(np.float32), sample.lidar2img.astype(np.float32)]
    return inputs


def random_weights(model, samples) -> None:
    """BatchNorm statistics from ``samples`` (train-mode passes), then anchor class layers with
    large random weights and a bias that puts the empty-cloud logits at <= -3."""
    reset_norm_statistics(model)  # cumulative average of the passes below
    model.train()
    with torch.no_grad():
        for s in samples:
            model(*(torch.from_numpy(x) for x in frame_inputs(model, s)))
    model.eval()
    heads = [m for m in model.modules() if type(m).__name__ == "AnchorHead"]
    seen = {}
    hooks = [h.register_forward_hook(lambda m, i, o: seen.__setitem__(id(m), i[0])) for h in heads]
    gen = torch.Generator().manual_seed(4)
    with torch.no_grad():
        for head in heads:
            w = head.conv_cls.weight
            w.copy_(torch.randn(w.shape, generator=gen) * 3 / w.shape[1] ** 0.5)
        empty = [np.zeros((0, 4), np.float32)] + frame_inputs(model, samples[0])[1:]
        model(*(torch.from_numpy(x) for x in empty))
        for head in heads:
            logits = head(seen[id(head)])[0]
            head.conv_cls.bias -= logits.reshape(-1, head.conv_cls.bias.shape[0]).max(0).values + 3.0
    for h in hooks:
        h.remove()
    if model.architecture == "point_rcnn":
        with torch.no_grad():
            model.seg_head[-1].bias.zero_()


def _p50(fn, frames) -> tuple[float, list]:
    """Median CPU ms of ``fn(frame)`` (one warm-up call per frame) and the outputs. CPU time of the
    process, not wall time: on a machine shared with other work, wall time counts the time the
    thread waited for a core (every runtime runs on one thread here)."""
    times, outs = [], []
    for f in frames:
        fn(f)
        t0 = time.process_time()
        outs.append(fn(f))
        times.append(1000 * (time.process_time() - t0))
    return float(np.median(times)), outs


def speed_row(model, onnx_path, samples, peak_gflops: float) -> dict:
    """Latency p50 of ORT, torch eager and OpenVINO on ``samples``, the GEMM split and agreement."""
    feeds_of = [frame_inputs(model, s) for s in samples]
    sess = session(onnx_path)
    names = [i.name for i in sess.get_inputs()]
    feeds = [dict(zip(names, f)) for f in feeds_of]
    ort_ms, ort_out = _p50(lambda f: sess.run(None, f), feeds)
    with torch.no_grad():
        torch_ms, _ = _p50(lambda f: model(*(torch.from_numpy(x) for x in f)), feeds_of)
    row = {"ort_p50_ms": ort_ms, "torch_p50_ms": torch_ms, **profile_frames(onnx_path, feeds)}
    # the profiler's per-node overhead inflates loops of small nodes (FPS, NMS): non-GEMM time is
    # the unprofiled latency less the GEMM nodes' time
    row["profiled_other_ms"], row["other_ms"] = row["other_ms"], max(ort_ms - row["gemm_ms"], 0.0)
    gemm_at_peak_ms = row["gemm_gflop"] / peak_gflops * 1000
    row["ort_over_gemm_peak"] = ort_ms / gemm_at_peak_ms if gemm_at_peak_ms else None
    try:
        import openvino as ov
    except ImportError:
        return row
    # f32: on a CPU with AVX-512 BF16 OpenVINO's default precision is bf16, other scores and boxes
    compiled = ov.Core().compile_model(str(onnx_path), "CPU", {"INFERENCE_NUM_THREADS": 1,
                                                               "INFERENCE_PRECISION_HINT": "f32"})
    ov_ms, ov_out = _p50(lambda f: (lambda res: [np.asarray(res[o]) for o in compiled.outputs])(compiled(f)), feeds)
    same = [outputs_agree({"boxes": a[0], "scores": a[1]}, {"boxes": b[0], "scores": b[1]})[0]
            for a, b in zip(ort_out, ov_out)]
    row.update(ov_p50_ms=ov_ms, ov_same_boxes=float(np.mean(same)))
    return row
