"""ONNX export following the ONNX contract (docs/models.md).

``export_onnx(model, path, metadata) -> dict`` exports one frame's forward with the dynamo
exporter (opset 18, dynamic number of points): it traces the network (or takes the traced graph
from ``models.graph_cache``, which makes a new checkpoint's export take seconds), runs the
exporter's optimiser, checks the file with ``onnx.checker``, drops the
exporter's stack-trace metadata (so that the bytes depend on the weights only), writes the
``sotif.*`` metadata_props and the op histogram (JSON under ``sotif.op_histogram``) and writes
the file atomically; it returns the op histogram. Camera models (``uses_camera``) take
``image`` [1, 3, H, W] and ``lidar2img`` [4, 4] too, with (H, W) from the model's
``image_hw`` attribute (or ``cfg.image_hw``).

``export_checkpoint(ckpt, out) -> Path`` exports a checkpoint of ``harness.train.train``.
"""
from __future__ import annotations

import collections
import contextlib
import json
import logging
import time
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch

from harness.core.files import atomic_write_bytes
from models import graph_cache
from models.base import Detector

OPSET = 18


class ExportError(RuntimeError):
    """The model could not be exported or the result breaks the contract."""


def image_hw(model: Detector) -> tuple[int, int]:
    hw = getattr(model, "image_hw", None) or getattr(getattr(model, "cfg", None), "image_hw", None)
    if hw is None:
        raise ExportError(f"{model.architecture}: camera model without image_hw (H, W)")
    return tuple(int(v) for v in hw)


def example_inputs(model: Detector, num_points: int = 2000, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Random inputs (points spread over the model's range; image/lidar2img for camera models)."""
    gen = torch.Generator().manual_seed(seed)
    pc_range = torch.tensor(model.cfg.pc_range, dtype=torch.float32)
    xyz = pc_range[:3] + torch.rand(num_points, 3, generator=gen) * (pc_range[3:] - pc_range[:3])
    points = torch.cat([xyz, torch.rand(num_points, 1, generator=gen)], dim=1)
    if not model.uses_camera:
        return (points,)
    h, w = image_hw(model)
    lidar2img = torch.eye(4)
    return points, torch.rand(1, 3, h, w, generator=gen), lidar2img


def op_histogram(model_proto: onnx.ModelProto) -> dict[str, int]:
    """Count of each op type, including ops inside Loop / If subgraphs."""
    counts: collections.Counter = collections.Counter()

    def walk(graph: onnx.GraphProto) -> None:
        for node in graph.node:
            counts[node.op_type] += 1
            for attr in node.attribute:
                if attr.type == onnx.AttributeProto.GRAPH:
                    walk(attr.g)
                for g in attr.graphs:
                    walk(g)

    walk(model_proto.graph)
    for fn in model_proto.functions:
        for node in fn.node:
            counts[node.op_type] += 1
    return dict(sorted(counts.items()))


def _graphs(proto: onnx.ModelProto):
    """The main graph and every Loop / If body in it."""
    stack = [proto.graph]
    while stack:
        graph = stack.pop()
        yield graph
        for node in graph.node:
            for attr in node.attribute:
                stack.extend([attr.g] if attr.type == onnx.AttributeProto.GRAPH else attr.graphs)


def strip_trace_metadata(proto: onnx.ModelProto) -> None:
    """Drop the exporter's per-node and per-value metadata (stack traces with this checkout's
    paths and the tracer's call counters), so that one checkpoint always gives the same bytes."""
    for graph in _graphs(proto):
        for items in (graph.node, graph.value_info, graph.input, graph.output, graph.initializer):
            for item in items:
                del item.metadata_props[:]
    for fn in proto.functions:
        for node in fn.node:
            del node.metadata_props[:]


def contract_metadata(model: Detector, metadata: dict[str, str]) -> dict[str, str]:
    meta = {"sotif.contract": "1", "sotif.architecture": model.architecture, "sotif.classes": "Car",
            "sotif.point_cloud_range": json.dumps([float(v) for v in model.cfg.pc_range]),
            "sotif.two_stage": str(bool(model.two_stage)).lower(),
            "sotif.uses_camera": str(bool(model.uses_camera)).lower()}
    meta.update({k: str(v) for k, v in metadata.items()})
    for key in ("sotif.profile", "sotif.data_hash", "sotif.config_hash"):
        meta.setdefault(key, "")
    return meta


@contextlib.contextmanager
def _quiet_exporter():
    """The exporter's chatter (torchvision absent, empty attribute lists, deprecations) off the
    progress display; errors still raise."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "onnx_ir", "onnxscript")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


class _Clock:
    """The export's stage lines with the seconds since it began (``say`` None: silent)."""

    def __init__(self, architecture: str, say):
        self.name, self.say, self.t0 = architecture, say, time.perf_counter()

    def seconds(self) -> float:
        return time.perf_counter() - self.t0

    def __call__(self, stage: str) -> None:
        if self.say is not None:
            self.say(f"export {self.name}: {stage} ({self.seconds():.0f} s)")


def trace_graph(model: Detector, inputs: tuple[torch.Tensor, ...]) -> onnx.ModelProto:
    """The traced, not yet optimised graph with the model's weights (the slow part of an export)."""
    import onnx_ir as ir

    dynamic = [{0: torch.export.Dim("num_points", min=0)}] + [None] * (len(inputs) - 1)
    with _quiet_exporter():
        try:
            program = torch.onnx.export(model, inputs, dynamo=True, input_names=list(model.input_names),
                                        output_names=list(model.output_names), dynamic_shapes=tuple(dynamic),
                                        opset_version=OPSET, optimize=False, verbose=False)
        except Exception as exc:
            raise ExportError(f"{model.architecture}: ONNX export failed: {exc}") from exc
    return ir.serde.serialize_model(program.model)


# onnxscript's rewrite rules the optimiser runs without: "SlicesSplit" (two Slices of one tensor -> one
# Split) matches its two-output pattern by trying every node of the graph against each Slice, quadratic in
# the graph's size: 60-80 % of the optimiser's time on the two-stage models (PV-RCNN's compact graph: 25.6 s
# -> 5.5 s), and it rewrites nothing in any of the seven graphs (tiny, compact and kitti: the same bytes with
# and without it, benchmarks/export_optimiser.py)
SKIPPED_REWRITE_RULES = ("SlicesSplit",)


@contextlib.contextmanager
def without_rewrite_rules(skip: tuple[str, ...]):
    """onnxscript's default rewrite rules without those named ``skip`` while the optimiser runs (it reads
    the module's tuple when called); an onnxscript without that tuple runs its rules unchanged."""
    import onnxscript.rewriter as rewriter

    rules = getattr(rewriter, "_DEFAULT_REWRITE_RULES", None)
    if not isinstance(rules, tuple) or not skip:
        yield
        return
    rewriter._DEFAULT_REWRITE_RULES = tuple(r for r in rules if getattr(r, "name", None) not in skip)
    try:
        yield
    finally:
        rewriter._DEFAULT_REWRITE_RULES = rules


def optimise_graph(traced: onnx.ModelProto, architecture: str,
                   skip: tuple[str, ...] = SKIPPED_REWRITE_RULES) -> onnx.ModelProto:
    """The exporter's optimiser (constant folding, which folds weights too) on a traced graph, read
    back from its proto whether it was traced now or came from the cache, so both give the same bytes;
    ``skip``: the onnxscript rewrite rules it runs without."""
    import onnx_ir as ir

    program = torch.onnx.ONNXProgram(ir.serde.deserialize_model(traced), None)
    with _quiet_exporter(), without_rewrite_rules(skip):
        try:
            program.optimize()
        except Exception as exc:
            raise ExportError(f"{architecture}: ONNX optimisation failed: {exc}") from exc
    return ir.serde.serialize_model(program.model)


def _traced_graph(model: Detector, clock: _Clock) -> onnx.ModelProto:
    """The traced graph from the graph cache (models.graph_cache), or traced now and cached."""
    key = graph_cache.cache_key(model, OPSET)
    cached = graph_cache.load(key, model)
    if cached is not None:
        clock("traced graph from the cache")
        return cached
    inputs = example_inputs(model)  # checks a camera model's image size before the slow part
    clock("tracing")
    traced = trace_graph(model, inputs)
    graph_cache.store(key, traced, model)
    return traced


def export_onnx(model: Detector, path, metadata: dict[str, str], say=None) -> dict[str, int]:
    """Export ``model`` to ONE self-contained ONNX file; returns the op histogram.

    ``say``: called with a line at each stage (tracing or cache, optimising, checking, writing)."""
    path = Path(path)
    model = model.eval().cpu()
    clock = _Clock(model.architecture, say)
    traced = _traced_graph(model, clock)
    clock("optimising")
    proto = optimise_graph(traced, model.architecture)
    clock("checking")
    onnx.checker.check_model(proto, full_check=True)
    strip_trace_metadata(proto)
    hist = op_histogram(proto)
    meta = contract_metadata(model, metadata)
    meta["sotif.op_histogram"] = json.dumps(hist)
    del proto.metadata_props[:]
    for key, value in meta.items():
        proto.metadata_props.add(key=key, value=value)
    clock("writing")
    atomic_write_bytes(path, proto.SerializeToString())  # what onnx.save writes, via temp file + rename
    if say is not None:
        say(f"export {model.architecture}: written in {clock.seconds():.0f} s")
    return hist


def export_checkpoint(ckpt, out, expected_model: str | None = None, say=None) -> Path:
    """Export a training checkpoint to ``out`` (.onnx) with its profile and hashes.

    ``expected_model``: refuse (ValueError) a checkpoint of another model; ``say``: as for
    ``export_onnx``."""
    from models.zoo import load_checkpoint

    model, meta = load_checkpoint(ckpt)
    if expected_model is not None and meta["model"] != expected_model:
        raise ValueError(f"{ckpt}: checkpoint of {meta['model']!r}, not {expected_model!r}")
    export_onnx(model, out, {"sotif.profile": meta.get("profile", ""),
                             "sotif.data_hash": meta.get("data_hash", ""),
                             "sotif.config_hash": meta.get("config_hash", ""),
                             "sotif.epoch": str(meta.get("epoch", "")),
                             **({"sotif.published": json.dumps(meta["published"])} if "published" in meta else {})},
                say=say)
    return Path(out)


def run_onnx(path, *inputs: np.ndarray) -> list[np.ndarray]:
    """Run an exported file with onnxruntime on numpy inputs (single-threaded, CPU)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    return sess.run(None, dict(zip(names, inputs)))


_INTEGER_TYPES = (onnx.TensorProto.INT64, onnx.TensorProto.INT32)


def integer_extremes(path, *inputs: np.ndarray) -> dict[str, int]:
    """Largest magnitude of every computed integer tensor of the main graph of an exported file on
    these inputs (onnxruntime, each one made a graph output; constants such as a Slice's "to the
    end" are left out): name -> max |value| (0 when empty).

    OpenVINO's CPU plugin computes int64 in int32, so every value here must stay below 2^31."""
    import onnxruntime as ort

    proto = onnx.load(str(path))
    typed = {v.name: v for v in proto.graph.value_info}
    computed = {o for node in proto.graph.node if node.op_type != "Constant" for o in node.output}
    names = [n for n, v in typed.items() if v.type.tensor_type.elem_type in _INTEGER_TYPES and n in computed]
    outputs = {o.name for o in proto.graph.output}
    proto.graph.output.extend(typed[n] for n in names if n not in outputs)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    sess = ort.InferenceSession(proto.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    feeds = dict(zip([i.name for i in sess.get_inputs()], inputs))
    values = sess.run(names, feeds)
    return {n: int(np.abs(v.astype(np.int64)).max()) if v.size else 0 for n, v in zip(names, values)}
