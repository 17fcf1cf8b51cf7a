"""Where an ONNX detector spends its time on one CPU thread: the GEMM nodes (Conv, ConvTranspose,
Gemm, MatMul and onnxruntime's fused forms of them) against everything else, from onnxruntime's
profiler, with the GEMM FLOPs of a frame counted from the node shapes the profiler records, and
the GEMM peak of this CPU measured on a large MatMul.

A Loop's own entry covers its body (FPS, NMS), whose nodes are therefore not counted again.
"""
from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
from onnx import TensorProto, helper

GEMM_OPS = {"Conv", "ConvTranspose", "Gemm", "MatMul", "FusedConv", "FusedGemm", "FusedMatMul"}


def session(path, threads: int = 1, profile_dir: Path | None = None) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    if profile_dir is not None:
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(profile_dir) / "ort")
    model = path if isinstance(path, bytes) else str(path)
    return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])


def _shapes(entries) -> list[list[int]]:
    return [next(iter(e.values())) for e in entries]


def gemm_flops(op: str, inputs: list[list[int]], outputs: list[list[int]]) -> float:
    """Multiply-adds x 2 of one GEMM-type node from its input / output shapes."""
    if op in ("Conv", "FusedConv"):  # weight (C_out, C_in / groups, k...): every output element
        return 2.0 * math.prod(outputs[0]) * math.prod(inputs[1][1:])
    if op == "ConvTranspose":  # weight (C_in, C_out / groups, k...): every input element
        return 2.0 * math.prod(inputs[0]) * math.prod(inputs[1][1:])
    a, out = inputs[0], outputs[0]  # out (..., M, N); MatMul contracts a's last axis
    k = math.prod(a) // out[0] if op in ("Gemm", "FusedGemm") else a[-1]  # Gemm's A: (M, K) or (K, M)
    return 2.0 * math.prod(out) * k


def _frame_split(nodes: list[dict]) -> tuple[float, float, float, dict[str, float]]:
    """GEMM ms, other ms, GEMM GFLOP and ms per non-GEMM op of one run's node events; the nodes
    a Loop / If body runs lie inside that node's own event and are not counted twice."""
    bodies = [(e["ts"], e["ts"] + e["dur"]) for e in nodes if e["args"]["op_name"] in ("Loop", "If", "Scan")]
    gemm = other = flops = 0.0
    ops: dict[str, float] = {}
    for e in nodes:
        op, ms = e["args"]["op_name"], e["dur"] / 1000.0
        if any(t0 < e["ts"] and e["ts"] + e["dur"] <= t1 for t0, t1 in bodies):
            continue
        if op in GEMM_OPS:
            gemm += ms
            flops += gemm_flops(op, _shapes(e["args"]["input_type_shape"]), _shapes(e["args"]["output_type_shape"]))
        else:
            other += ms
            ops[op] = ops.get(op, 0.0) + ms
    return gemm, other, flops / 1e9, ops


def profile_frames(path, feeds: list[dict], threads: int = 1) -> dict:
    """Per-frame medians over ``feeds`` (one profiled run each, after one warm-up run):
    ``gemm_ms``, ``other_ms`` (node times), ``gemm_gflop`` and the slowest non-GEMM ops.

    The profiler's node times are wall times; on a machine shared with other work they are scaled
    by the run's CPU time over its wall time (the share of the run the thread spent on a core), so
    that they add up like the CPU-time latencies of ``benchmarks/model_speed.py``."""
    cpu = []
    with tempfile.TemporaryDirectory() as tmp:
        sess = session(path, threads, Path(tmp))
        sess.run(None, feeds[0])
        for feed in feeds:
            t0 = time.process_time()
            sess.run(None, feed)
            cpu.append(1000 * (time.process_time() - t0))
        events = json.loads(Path(sess.end_profiling()).read_text())
    nodes = [e for e in events if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time")]
    frames = []
    for run, cpu_ms in zip([e for e in events if e.get("name") == "model_run"][1:], cpu):  # [0]: the warm-up
        t0, t1 = run["ts"], run["ts"] + run["dur"]
        busy = min(1.0, cpu_ms / threads / (run["dur"] / 1000.0))  # share of the wall time its threads were on a core
        gemm, other, gflop, ops = _frame_split([e for e in nodes if t0 <= e["ts"] <= t1])
        frames.append((gemm * busy, other * busy, gflop, {op: ms * busy for op, ms in ops.items()}))
    top: dict[str, float] = {}
    for *_, ops in frames:
        for op, ms in ops.items():
            top[op] = top.get(op, 0.0) + ms / len(frames)
    return {"gemm_ms": float(np.median([f[0] for f in frames])), "other_ms": float(np.median([f[1] for f in frames])),
            "gemm_gflop": float(np.median([f[2] for f in frames])),
            "top_other": sorted(top.items(), key=lambda kv: -kv[1])[:4]}


def gemm_peak(n: int = 2048, repeats: int = 5, threads: int = 1) -> float:
    """GFLOP/s of onnxruntime's MatMul on (n, n) x (n, n) float32, best of ``repeats``."""
    a = helper.make_tensor_value_info("a", TensorProto.FLOAT, [n, n])
    c = helper.make_tensor_value_info("c", TensorProto.FLOAT, [n, n])
    b = helper.make_tensor("b", TensorProto.FLOAT, [n, n],
                           np.random.default_rng(0).random((n, n), np.float32).tobytes(), raw=True)
    graph = helper.make_graph([helper.make_node("MatMul", ["a", "b"], ["c"])], "peak", [a], [c], [b])
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    sess = session(proto.SerializeToString(), threads)
    x = np.random.default_rng(1).random((n, n), np.float32)
    return 2.0 * n ** 3 / cpu_ms(sess, {"a": x}, repeats) / 1e6


def cpu_ms(sess: ort.InferenceSession, feeds: dict, repeats: int) -> float:
    """Best CPU time of ``repeats`` runs after one warm-up run, ms (CPU time: what the core
    spent, not a share of the machine)."""
    sess.run(None, feeds)
    best = math.inf
    for _ in range(repeats):
        t0 = time.process_time()
        sess.run(None, feeds)
        best = min(best, time.process_time() - t0)
    return 1000.0 * best
