"""Inference through the ONNX contract: any conforming file runs here, ours or a user's.

The harness knows the contract (docs/models.md), not the models: ``check_contract`` reads a file's
inputs, outputs and metadata and refuses a file that breaks the contract; ``OnnxDetector`` runs
it in onnxruntime (or OpenVINO); ``predict`` runs a data set split and writes KITTI result
files (camera-frame labels with projected 2D boxes) plus per-frame latency.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnx

from harness.core.files import atomic_write_text, folder_lock, sha256_file
from harness.core.kitti import (KittiError, Labels, check_image_fits_calib, frame_path, image_size, read_calib,
                                read_image, read_image_set, read_points, write_labels)

CONTRACT_VERSION = "1"
REQUIRED_OUTPUTS = ("boxes", "scores")
STAGE_OUTPUTS = ("rois", "roi_scores")
STANDARD_DOMAINS = ("", "ai.onnx", "ai.onnx.ml")
MIN_OPSET = 18
REQUIRED_METADATA = ("sotif.contract", "sotif.architecture", "sotif.classes", "sotif.point_cloud_range")
PROVENANCE_METADATA = ("sotif.data_hash", "sotif.config_hash")  # optional: our exports write them, a user's may not


class ContractError(ValueError):
    """An ONNX file does not follow the contract; the message names the file and the rule."""

    def __init__(self, path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path, self.problem = Path(path), problem

    def __reduce__(self):  # pickled whole (a job process of `run` raises it in the run's process)
        return type(self), (self.path, self.problem)


@dataclass
class ContractInfo:
    path: Path
    inputs: dict  # name -> list of dims (int or str)
    outputs: dict
    metadata: dict
    sha256: str
    op_histogram: dict = field(default_factory=dict)

    @property
    def uses_camera(self) -> bool:
        return "image" in self.inputs

    @property
    def two_stage(self) -> bool:
        return all(k in self.outputs for k in STAGE_OUTPUTS)

    @property
    def architecture(self) -> str:
        return self.metadata.get("sotif.architecture", self.path.stem)

    @property
    def provenance(self) -> dict:
        """The optional provenance keys the file carries (``data_hash``, ``config_hash``), without empty ones."""
        return {k.removeprefix("sotif."): self.metadata[k] for k in PROVENANCE_METADATA if self.metadata.get(k)}

    def image_size(self) -> tuple[int, int] | None:
        """(H, W) the camera input expects, when fixed."""
        if not self.uses_camera:
            return None
        h, w = self.inputs["image"][2:4]
        return (h, w) if isinstance(h, int) and isinstance(w, int) else None


def _dims(value_info) -> list:
    shape = value_info.type.tensor_type.shape
    return [d.dim_value if d.HasField("dim_value") else (d.dim_param or "?") for d in shape.dim]


def _elem(value_info) -> int:
    return value_info.type.tensor_type.elem_type


def _subgraphs(node):
    for attr in node.attribute:
        if attr.type == onnx.AttributeProto.GRAPH:
            yield attr.g
        elif attr.type == onnx.AttributeProto.GRAPHS:
            yield from attr.graphs


def _all_nodes(nodes):
    """Every node, with those of Loop / If / Scan bodies at any depth."""
    for node in nodes:
        yield node
        for graph in _subgraphs(node):
            yield from _all_nodes(graph.node)


def _all_tensors(model):
    """Every stored tensor: the initializers of the graph and of every subgraph, and the tensor
    attributes (Constant values) of every node, in functions too."""
    def of_graph(graph):
        yield from graph.initializer
        yield from (t.values for t in graph.sparse_initializer)
        yield from of_nodes(graph.node)

    def of_nodes(nodes):
        for node in nodes:
            for attr in node.attribute:
                if attr.type == onnx.AttributeProto.TENSOR:
                    yield attr.t
                elif attr.type == onnx.AttributeProto.TENSORS:
                    yield from attr.tensors
            for graph in _subgraphs(node):
                yield from of_graph(graph)
    yield from of_graph(model.graph)
    for function in model.functions:
        yield from of_nodes(function.node)


def _type_name(elem: int) -> str:
    try:
        return onnx.helper.tensor_dtype_to_np_dtype(elem).name
    except (KeyError, TypeError, ValueError):  # undefined, or no numpy twin (bfloat16, float8 ...)
        return onnx.TensorProto.DataType.Name(elem).lower() if elem in onnx.TensorProto.DataType.values() else "undefined"


def runtime_reason(exc: Exception, limit: int = 400) -> str:
    """The informative part of a runtime's message: without OpenVINO's "Exception from file:line"
    frames, on one line, at most ``limit`` characters."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip() and not ln.startswith("Exception from ")]
    return " ".join(lines)[:limit] or type(exc).__name__


def _check_io(path, model) -> tuple[dict, dict]:
    f32 = onnx.TensorProto.FLOAT
    inputs = {i.name: i for i in model.graph.input}
    outputs = {o.name: o for o in model.graph.output}
    if "points" not in inputs:
        raise ContractError(path, f"no input named 'points' (inputs: {', '.join(inputs) or 'none'})")
    pts = inputs["points"]
    if _elem(pts) != f32 or len(_dims(pts)) != 2 or _dims(pts)[1] != 4:
        raise ContractError(path, f"input 'points' must be float32 [N, 4], got {_type_name(_elem(pts))} {_dims(pts)}")
    if isinstance(_dims(pts)[0], int):
        raise ContractError(path, "input 'points' must have a dynamic first dimension (any number of points)")
    extra = set(inputs) - {"points", "image", "lidar2img"}
    if extra:
        raise ContractError(path, f"unexpected input(s) {sorted(extra)}; the contract allows points, image, lidar2img")
    if ("image" in inputs) != ("lidar2img" in inputs):
        raise ContractError(path, "camera models need both 'image' [1, 3, H, W] and 'lidar2img' [4, 4]")
    if "image" in inputs:
        image, l2i = inputs["image"], inputs["lidar2img"]
        d = _dims(image)
        if (_elem(image) != f32 or len(d) != 4 or (isinstance(d[0], int) and d[0] != 1)
                or (isinstance(d[1], int) and d[1] != 3)):
            raise ContractError(path, f"input 'image' must be float32 [1, 3, H, W], got {_type_name(_elem(image))} "
                                      f"{_dims(image)}")
        if _elem(l2i) != f32 or _dims(l2i) != [4, 4]:
            raise ContractError(path, f"input 'lidar2img' must be float32 [4, 4], got {_type_name(_elem(l2i))} "
                                      f"{_dims(l2i)}")
    for name in REQUIRED_OUTPUTS:
        if name not in outputs:
            raise ContractError(path, f"no output named '{name}' (outputs: {', '.join(outputs) or 'none'})")
    shapes = {"boxes": 2, "scores": 1, "rois": 2, "roi_scores": 1, "rcnn_boxes": 2}
    for name, rank in shapes.items():
        if name in outputs:
            d = _dims(outputs[name])
            if _elem(outputs[name]) != f32 or len(d) != rank or (rank == 2 and d[1] != 7):
                raise ContractError(path, f"output '{name}' must be float32 {'[M, 7]' if rank == 2 else '[M]'}, "
                                          f"got {_type_name(_elem(outputs[name]))} {d}")
    if ("rois" in outputs) != ("roi_scores" in outputs):
        raise ContractError(path, "two-stage outputs come in pairs: 'rois' and 'roi_scores'")
    return ({k: _dims(v) for k, v in inputs.items()}, {k: _dims(v) for k, v in outputs.items()})


def check_contract(path) -> ContractInfo:
    """Validate an ONNX file against the ONNX contract (docs/models.md); raise ContractError if it breaks it."""
    path = Path(path)
    if not path.is_file():
        raise ContractError(path, "is a folder, not an ONNX file" if path.is_dir() else "file not found")
    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception as e:  # noqa: BLE001 - onnx raises several kinds of decode errors
        raise ContractError(path, f"not a readable ONNX model ({type(e).__name__}: {e})") from None
    for tensor in _all_tensors(model):
        if tensor.data_location == onnx.TensorProto.EXTERNAL:
            raise ContractError(path, f"tensor '{tensor.name}' is stored in an external file; the contract needs "
                                      "one self-contained file")
    if model.ByteSize() == 0:
        raise ContractError(path, "empty: no ONNX model in it")
    opsets = {o.domain: o.version for o in model.opset_import}
    opset = opsets.get("", opsets.get("ai.onnx", 0))
    if opset < MIN_OPSET:
        raise ContractError(path, f"opset {opset} of the default domain; the contract needs opset >= {MIN_OPSET}")
    try:
        onnx.checker.check_model(model, full_check=True)
    except (onnx.checker.ValidationError, onnx.shape_inference.InferenceError) as e:
        raise ContractError(path, f"onnx.checker rejects the model: {str(e).splitlines()[0]}") from None
    inputs, outputs = _check_io(path, model)
    local = {(f.domain, f.name) for f in model.functions}
    bodies = [n for f in model.functions for n in _all_nodes(f.node)]
    for node in [*_all_nodes(model.graph.node), *bodies]:
        if node.domain not in STANDARD_DOMAINS and (node.domain, node.op_type) not in local:
            raise ContractError(path, f"node '{node.name}' uses the non-standard op {node.domain}::{node.op_type}")
    hist: dict[str, int] = {}
    for node in model.graph.node:
        hist[node.op_type] = hist.get(node.op_type, 0) + 1
    meta = {p.key: p.value for p in model.metadata_props}
    if meta.get("sotif.contract") != CONTRACT_VERSION:
        raise ContractError(path, f"metadata 'sotif.contract' must be \"{CONTRACT_VERSION}\", got {meta.get('sotif.contract')!r}")
    missing = [k for k in REQUIRED_METADATA if k not in meta]
    if missing:
        raise ContractError(path, f"metadata_props lack {', '.join(missing)} (the contract needs {', '.join(REQUIRED_METADATA)})")
    if not meta["sotif.architecture"].strip():
        raise ContractError(path, "metadata 'sotif.architecture' is empty; it names the detector in every table")
    if [c.strip() for c in meta["sotif.classes"].split(",")] != ["Car"]:
        raise ContractError(path, f"metadata 'sotif.classes' must be \"Car\" (the outputs carry no class, and every box "
                                  f"is scored as a car), got {meta['sotif.classes']!r}")
    if point_cloud_range(meta["sotif.point_cloud_range"]) is None:
        raise ContractError(path, "metadata 'sotif.point_cloud_range' must be six numbers x_min, y_min, z_min, x_max, "
                                  "y_max, z_max (a JSON list or comma-separated), each min below its max, got "
                                  f"{meta['sotif.point_cloud_range']!r}")
    return ContractInfo(path, inputs, outputs, meta, sha256_file(path), dict(sorted(hist.items())))


def point_cloud_range(text: str) -> list[float] | None:
    """The six numbers of ``sotif.point_cloud_range``, a JSON list ("[0, -40, -3, 70.4, 40, 1]") or
    comma-separated ("0,-40,-3,70.4,40,1"); None unless six finite numbers with each min below its max."""
    try:
        values = json.loads(text) if text.strip().startswith("[") else text.split(",")
        pc_range = [float(v) for v in values]
    except (ValueError, TypeError):
        return None
    ok = len(pc_range) == 6 and all(lo < hi for lo, hi in zip(pc_range[:3], pc_range[3:]))
    return pc_range if ok and all(math.isfinite(v) for v in pc_range) else None


class OnnxDetector:
    """A contract-conforming ONNX detector behind onnxruntime (default) or OpenVINO."""

    def __init__(self, path, runtime: str = "onnxruntime", threads: int | None = None):
        self.info = check_contract(path)
        self.runtime = runtime
        if runtime == "onnxruntime":
            import onnxruntime as ort
            opts = ort.SessionOptions()
            if threads:
                opts.intra_op_num_threads = threads
            opts.log_severity_level = 3
            try:
                self._sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
            except Exception as e:  # noqa: BLE001 - onnxruntime's load errors share no base class but Exception
                raise ContractError(path, f"onnxruntime cannot load it: {runtime_reason(e)}") from e
            self.output_names = [o.name for o in self._sess.get_outputs()]
            self._run = lambda feeds: dict(zip(self.output_names, self._sess.run(None, feeds)))
        elif runtime == "openvino":
            try:
                import openvino as ov
            except ImportError:
                raise ValueError("--runtime openvino needs the optional extra: pip install 'sotif-bench[openvino]'") from None
            try:
                # f32: on CPUs with AVX-512 BF16 OpenVINO's default inference precision is bf16, which
                # would make every comparison with onnxruntime a comparison of precisions
                compiled = ov.Core().compile_model(str(path), "CPU", {"INFERENCE_PRECISION_HINT": "f32"})
            except Exception as e:  # noqa: BLE001 - as for onnxruntime
                raise ContractError(path, f"OpenVINO cannot load it: {runtime_reason(e)}") from e
            # an output tensor can carry several names in OpenVINO: keep the graph's output order
            self.output_names = list(self.info.outputs)

            def run_openvino(feeds):
                res = compiled(feeds)
                return {k: np.asarray(res[compiled.outputs[i]]) for i, k in enumerate(self.output_names)}
            self._run = run_openvino
        else:
            raise ValueError(f"unknown runtime {runtime!r}; expected onnxruntime or openvino")

    def __call__(self, points: np.ndarray, image: np.ndarray | None = None,
                 lidar2img: np.ndarray | None = None) -> dict:
        feeds = {"points": np.ascontiguousarray(points, dtype=np.float32)}
        if self.info.uses_camera:
            if image is None or lidar2img is None:
                raise ValueError(f"{self.info.path}: this model needs a camera image and lidar2img")
            feeds["image"] = np.ascontiguousarray(image, dtype=np.float32)
            feeds["lidar2img"] = np.ascontiguousarray(lidar2img, dtype=np.float32)
        try:
            out = self._run(feeds)
        except Exception as e:  # noqa: BLE001 - the runtime's errors on this file's graph are the file's
            raise ValueError(f"{self.info.path}: {self.runtime} failed on an input of {len(points)} points: "
                             f"{runtime_reason(e)}") from e
        for name in out:
            out[name] = np.asarray(out[name], dtype=np.float32)
            if not np.isfinite(out[name]).all():
                raise ValueError(f"{self.info.path}: output '{name}' contains NaN or inf")
        for boxes, scores in (("boxes", "scores"), ("rois", "roi_scores")):
            if boxes in out and (out[boxes].ndim != 2 or out[boxes].shape[1] != 7 or out[scores].ndim != 1
                                 or len(out[scores]) != len(out[boxes])):
                raise ValueError(f"{self.info.path}: outputs '{boxes}' {list(out[boxes].shape)} and '{scores}' "
                                 f"{list(out[scores].shape)} are not [M, 7] and [M] with the same M")
            if boxes in out and (out[boxes][:, 3:6] <= 0).any():
                i = int(np.flatnonzero((out[boxes][:, 3:6] <= 0).any(axis=1))[0])
                raise ValueError(f"{self.info.path}: output '{boxes}' has a box with a size <= 0 (box {i}: l w h "
                                 f"{' '.join(f'{v:g}' for v in out[boxes][i, 3:6])})")
        return out


def image_input(rgb: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    """(H, W, 3) uint8 -> (1, 3, H', W') float32 in [0, 1], resized to the model's fixed size."""
    if size is not None and rgb.shape[:2] != tuple(size):
        from PIL import Image
        rgb = np.asarray(Image.fromarray(rgb).resize((size[1], size[0]), Image.BILINEAR))
    return (rgb.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]


def scale_lidar2img(lidar2img: np.ndarray, from_hw, to_hw) -> np.ndarray:
    """lidar2img for an image resized from (H, W) to (H', W')."""
    s = np.diag([to_hw[1] / from_hw[1], to_hw[0] / from_hw[0], 1.0, 1.0])
    return (s @ lidar2img).astype(np.float32)


def boxes_to_results(boxes: np.ndarray, scores: np.ndarray, calib, image_hw) -> Labels:
    """KITTI result labels of LiDAR boxes, keeping those visible in the camera image."""
    labels = Labels.from_lidar(boxes, calib, ["Car"] * len(boxes), score=scores,
                               image_size=(image_hw[1], image_hw[0]))
    visible = ((labels.location[:, 2] > 0) & (labels.bbox[:, 2] > labels.bbox[:, 0])
               & (labels.bbox[:, 3] > labels.bbox[:, 1]))
    return labels.select(visible)


def frame_inputs(det: OnnxDetector, root: Path, fid: str):
    """One frame as ``det`` takes it: (points, calib, image or None, lidar2img or None, the image's (H, W))."""
    points = read_points(frame_path(root, "velodyne", fid))
    calib = read_calib(frame_path(root, "calib", fid))
    img_path = frame_path(root, "image_2", fid)
    hw = (375, 1242)
    image = l2i = None
    if det.info.uses_camera or img_path.is_file():
        if det.info.uses_camera:
            rgb = read_image(img_path)
            hw = rgb.shape[:2]
        else:  # the image's size only: the camera's view the results are kept in
            hw = image_size(img_path)
        check_image_fits_calib(img_path, hw, calib, frame_path(root, "calib", fid))
        if det.info.uses_camera:
            size = det.info.image_size()
            image = image_input(rgb, size)
            l2i = scale_lidar2img(calib.lidar2img(), hw, size or hw)
    return points, calib, image, l2i, hw


def _inputs_digest(root: Path, ids) -> str:
    """Identity of the frames a prediction reads: the data set's path and each input file's
    size and modification time (a missing file counts as such; reading it fails later)."""
    h = hashlib.sha256(str(root.resolve()).encode())
    for fid in ids:
        for kind in ("velodyne", "calib", "image_2"):
            p = frame_path(root, kind, fid)
            try:
                st = p.stat()
                h.update(f"{p.name} {st.st_size} {st.st_mtime_ns}\n".encode())
            except FileNotFoundError:
                h.update(f"{p.name} -\n".encode())
    return h.hexdigest()[:16]


def _result_files(out: Path) -> list[Path]:
    """The files ``predict`` writes per frame: ``<id>.txt`` in ``out``, ``rois/`` and ``rcnn/``."""
    return [p for d in (out, out / "rois", out / "rcnn") if d.is_dir()
            for p in sorted(d.glob("*.txt")) if p.stem.isdigit()]


def predict(onnx_path, data, out, split: str | Path = "test", runtime: str = "onnxruntime",
            progress: bool = True, threads: int | None = None) -> dict:
    """Run a split (a name in ``data/ImageSets``, or an ImageSets file) through an ONNX detector;
    write ``out/<id>.txt`` (+ ``rois/``, ``rcnn/``)
    and ``out/predict.json`` (latency p50/p90, frames/s). Resumes an interrupted run of the same
    model, runtime, split and data set (``out/.progress.json``); results of another one are
    replaced, and result files no earlier ``predict`` recorded are refused, not reused. A second
    ``predict`` into the same folder while this one runs is refused (``out/.lock``)."""
    data, out = Path(data), Path(out)
    det = OnnxDetector(onnx_path, runtime=runtime, threads=threads)
    split_path = split if isinstance(split, Path) else data / "ImageSets" / f"{split}.txt"
    ids = read_image_set(split_path)
    if not ids:
        raise KittiError(split_path, "lists no frames: nothing to predict")
    stamp = {"onnx_sha256": det.info.sha256, "runtime": runtime, "split": str(split), "data": _inputs_digest(data, ids)}
    _refuse_unrecorded_results(out)  # before the lock file: a refused folder stays as it was
    out.mkdir(parents=True, exist_ok=True)
    with folder_lock(out, "predict"):
        return _predict_frames(det, data, out, ids, stamp, progress)


def _refuse_unrecorded_results(out: Path) -> None:
    found = [] if (out / ".progress.json").is_file() else (
        _result_files(out) + [p for p in (out / "predict.json", out / "latency_ms.csv") if p.exists()])
    if found:
        raise ValueError(f"{out}: holds result files ({found[0].name}, ...) that no earlier "
                         "'sotif-bench predict' into this folder recorded; remove them or choose another --out")


def _read_journal(path: Path) -> dict[str, dict]:
    """``predict``'s per-frame record (``out/.frames.jsonl``: one JSON line per predicted frame,
    appended before its result files are written): frame id -> latency and point count. A line
    cut off by a kill is skipped; that frame has no result file yet and is predicted again."""
    rows = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
                rows[str(row["frame_id"])] = row
            except (ValueError, KeyError, TypeError):
                continue
    return rows


def _predict_frames(det: OnnxDetector, data: Path, out: Path, ids: list[str], stamp: dict, progress: bool) -> dict:
    from tqdm import tqdm

    progress_file, journal = out / ".progress.json", out / ".frames.jsonl"
    if progress_file.is_file():
        try:
            same = json.loads(progress_file.read_text()) == stamp
        except ValueError:
            same = False
        if not same:  # results of another model, runtime, split or data set: start over
            recorded = set(_read_journal(journal))  # frames the earlier predict wrote (recorded before their files)
            foreign = [p for p in _result_files(out) if p.stem not in recorded]
            if foreign:
                raise ValueError(f"{out}: holds result files ({foreign[0].relative_to(out)}, ...) that the earlier "
                                 "'sotif-bench predict' into this folder did not write; remove them or choose "
                                 "another --out")
            for old in _result_files(out):
                old.unlink()
            journal.unlink(missing_ok=True)
    else:
        _refuse_unrecorded_results(out)
        journal.unlink(missing_ok=True)  # a record without its stamp belongs to no results here
    atomic_write_text(progress_file, json.dumps(stamp))
    ran = False  # a frame was predicted in this call
    with open(journal, "a+b") as record:
        if record.tell() and (record.seek(-1, os.SEEK_END), record.read(1))[1] != b"\n":
            record.write(b"\n")  # end a line a kill cut off, so the next record starts its own
        for fid in tqdm(ids, desc=f"predict {det.info.architecture}", disable=not progress, unit="frame"):
            if (out / f"{fid}.txt").is_file():
                continue
            points, calib, image, l2i, hw = frame_inputs(det, data, fid)
            try:
                if not ran:
                    det(points, image, l2i)  # warm-up: first-run allocations are not latency
                t0 = time.perf_counter()
                res = det(points, image, l2i)
                ms = 1000 * (time.perf_counter() - t0)
            except ValueError as e:  # the model failed on this frame: name the frame's scan as well
                raise ValueError(f"{e} (frame {fid}: {frame_path(data, 'velodyne', fid)})") from e
            # recorded before its files, so that every result file here is one predict wrote
            record.write(json.dumps({"frame_id": fid, "latency_ms": ms, "n_points": len(points)}).encode() + b"\n")
            record.flush()
            if det.info.two_stage:
                write_labels(out / "rois" / f"{fid}.txt", boxes_to_results(res["rois"], res["roi_scores"], calib, hw))
                if "rcnn_boxes" in res:
                    write_labels(out / "rcnn" / f"{fid}.txt",
                                 boxes_to_results(res["rcnn_boxes"], res["roi_scores"], calib, hw))
            write_labels(out / f"{fid}.txt", boxes_to_results(res["boxes"], res["scores"], calib, hw))
            ran = True
    # the timings of every session that predicted frames of this folder, in the split's order
    rows = _read_journal(journal)
    timed = [rows[fid] for fid in ids if fid in rows and (out / f"{fid}.txt").is_file()]
    if not ran and not timed and (out / "predict.json").is_file():
        return json.loads((out / "predict.json").read_text())  # finished before frames were recorded
    latencies = [r["latency_ms"] for r in timed]
    summary = latency_summary(latencies) | {
        "n_frames": len(ids), "n_points_mean": float(np.mean([r["n_points"] for r in timed])) if timed else None,
        **stamp, "architecture": det.info.architecture, "two_stage": det.info.two_stage,
        "uses_camera": det.info.uses_camera, "provenance": det.info.provenance}
    atomic_write_text(out / "latency_ms.csv", "frame_id,latency_ms\n"
                      + "".join(f"{r['frame_id']},{r['latency_ms']:.4f}\n" for r in timed))
    atomic_write_text(out / "predict.json", json.dumps(summary, indent=1))
    return summary


def latency_summary(latencies_ms) -> dict:
    lat = np.asarray(latencies_ms, dtype=np.float64)
    if lat.size == 0:
        return {"latency_ms_p50": None, "latency_ms_p90": None, "latency_ms_mean": None, "fps": None, "n_timed": 0}
    return {"latency_ms_p50": float(np.percentile(lat, 50)), "latency_ms_p90": float(np.percentile(lat, 90)),
            "latency_ms_mean": float(lat.mean()), "fps": float(1000.0 / lat.mean()), "n_timed": int(lat.size)}
