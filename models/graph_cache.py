"""A per-user cache of traced ONNX graphs, so that a new checkpoint of a known network exports in
seconds instead of minutes.

Tracing (``torch.export`` and the translation to ONNX) takes nearly all of an export's time, and
its result does not depend on the weights: ``torch.export`` traces with fake parameters and
buffers, and the traced graph holds each of them as an initializer named by its state-dict name
(``backbone2d.blocks.0.0.weight``), untransformed. The foldings that do depend on the weights
(a BatchNorm's square root, convolution weights concatenated, a transposed matrix) happen later,
in the optimiser, which ``models.export`` runs on every export, cached or not. So an entry is the
traced graph with the weights' data removed; an export fills in its model's tensors by name.

- ``graph_code() -> str``: a digest of the code of the ``models`` package's sources (``code_text``:
  comments, docstrings, layout and the module paths of imports from harness/simulator left out).
- ``cache_key(model) -> str | None``: the digest of what the traced graph depends on: the code
  (``graph_code``, and the code of the model's class's file), the class, its config (``asdict``), the
  torch / onnx / onnxscript / onnx_ir versions and the opset; None for a model whose config is
  not a dataclass (not cached).
- ``cache_dir() -> Path | None``: ``$SOTIF_BENCH_GRAPH_CACHE`` if set ("off" disables the
  cache), else ``$XDG_CACHE_HOME/sotif-bench/graphs`` (``~/.cache/sotif-bench/graphs``).
- ``load(key, model) -> ModelProto | None``: the cached graph with ``model``'s weights, or None
  when there is no entry or it is unusable (damaged, or weights of other names, shapes or dtypes:
  then the export traces again and writes a new entry).
- ``store(key, traced, model) -> bool``: write the entry, but only where the proof holds that
  filling ``model``'s own weights into it gives back ``traced`` byte for byte (every weight an
  initializer under its own name and its own bytes); False where it does not (no entry).

An entry file is the SHA-256 of its payload (64 hex digits and a newline) and the payload, a
serialised ``onnx.ModelProto``; it is written atomically, and one whose digest does not match is
ignored.
"""
from __future__ import annotations

import ast
import dataclasses
import hashlib
import inspect
import json
import os
import re
from importlib import metadata
from pathlib import Path

import onnx
import torch

from harness.core.files import atomic_write_bytes

ENV = "SOTIF_BENCH_GRAPH_CACHE"
FORMAT = 1  # of an entry; a new layout changes every key
PACKAGE = Path(__file__).parent
OUTSIDE = ("harness", "simulator")  # project packages whose module paths are not code of the graph


def graph_code(folder: Path = PACKAGE) -> str:
    """A digest of the code of the ``models`` package. A checkpoint's ONNX graph is a function of the
    checkpoint and this code, so a changed network or exporter exports again; an edit that changes
    no code (a comment, a docstring, a moved harness name) does not."""
    digest = hashlib.sha256()
    for path in sorted(Path(folder).glob("*.py")):
        digest.update(path.name.encode() + b"\0" + code_text(path.read_text(encoding="utf-8")).encode())
    return digest.hexdigest()[:16]


def code_text(source: str) -> str:
    """``source`` as the code it runs: without comments, docstrings and layout, and with the module
    path of a ``from`` import out of harness or simulator left out (the graph does not depend on
    which of their modules holds a name, and their sources are not in the digest either)."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            first = node.body[0] if node.body else None
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                node.body = node.body[1:] or [ast.Pass()]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module.split(".")[0] in OUTSIDE:
            node.module = "project"
    return ast.unparse(tree)


def _versions() -> dict[str, str]:
    return {name: metadata.version(name) for name in ("torch", "onnx", "onnxscript", "onnx_ir")}


def cache_key(model: torch.nn.Module, opset: int) -> str | None:
    cfg = getattr(model, "cfg", None)
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        return None
    cls = type(model)
    source = code_text(Path(inspect.getsourcefile(cls)).read_text(encoding="utf-8"))
    ident = {"format": FORMAT, "code": graph_code(), "class": f"{cls.__module__}.{cls.__qualname__}",
             "class_file": hashlib.sha256(source.encode()).hexdigest(), "config": dataclasses.asdict(cfg),
             "structure": _structure(model), "versions": _versions(), "opset": opset}
    return hashlib.sha256(json.dumps(ident, sort_keys=True, default=repr).encode()).hexdigest()[:32]


def _structure(model: torch.nn.Module) -> dict:
    """What else shapes the graph besides the model's own config: the module tree as printed, every
    submodule's dataclass settings and the names, shapes and dtypes of the weights (two models of one
    class whose heads are configured apart must never share an entry). A BatchNorm's ``momentum`` is
    left out of the printed tree: it weighs the running statistics of train-mode passes and is not in
    the traced (eval-mode) graph, and ``models.base.reset_norm_statistics`` sets it to None."""
    settings = {name: dataclasses.asdict(value) for mod_name, mod in model.named_modules()
                for attr, value in vars(mod).items() if dataclasses.is_dataclass(value) and not isinstance(value, type)
                for name in [f"{mod_name}.{attr}"]}
    tensors = [(k, tuple(v.shape), str(v.dtype)) for k, v in model.state_dict().items()]
    return {"modules": _MOMENTUM.sub("", repr(model)), "settings": settings, "tensors": tensors}


_MOMENTUM = re.compile(r"momentum=[^,)]*, ?")


def cache_dir() -> Path | None:
    value = os.environ.get(ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "off", "0", "none") else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "sotif-bench" / "graphs"


def _entry(key: str) -> Path | None:
    root = cache_dir()
    return None if root is None else root / f"{key}.graph"


def weights(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """Every parameter and buffer (non-persistent ones too) by its state-dict name."""
    named = dict(model.named_parameters(remove_duplicate=False))
    named.update(model.named_buffers(remove_duplicate=False))
    return named


_ONNX_TYPES = {torch.float32: onnx.TensorProto.FLOAT, torch.float64: onnx.TensorProto.DOUBLE,
               torch.float16: onnx.TensorProto.FLOAT16, torch.int64: onnx.TensorProto.INT64,
               torch.int32: onnx.TensorProto.INT32, torch.uint8: onnx.TensorProto.UINT8,
               torch.int8: onnx.TensorProto.INT8, torch.bool: onnx.TensorProto.BOOL}


def _raw(tensor: torch.Tensor) -> bytes:
    """A tensor's bytes as an initializer's ``raw_data`` holds them (little-endian, row-major)."""
    flat = tensor.detach().cpu().contiguous().reshape(-1)
    return flat.view(torch.uint8).numpy().tobytes() if flat.numel() else b""


def _fill(empty: onnx.ModelProto, model: torch.nn.Module) -> onnx.ModelProto | None:
    """``empty`` with ``model``'s weights written into its initializers of the same names; None when
    one does not fit (another shape or dtype, or a name the model lacks)."""
    tensors = weights(model)
    proto = onnx.ModelProto()
    proto.CopyFrom(empty)
    for init in proto.graph.initializer:
        if init.HasField("raw_data") or init.name not in tensors:
            continue  # a constant of the code, kept as traced
        tensor = tensors[init.name]
        if list(init.dims) != list(tensor.shape) or init.data_type != _ONNX_TYPES.get(tensor.dtype):
            return None
        init.raw_data = _raw(tensor)
    return proto


def _strip(traced: onnx.ModelProto, model: torch.nn.Module) -> onnx.ModelProto:
    names = set(weights(model))
    empty = onnx.ModelProto()
    empty.CopyFrom(traced)
    for init in empty.graph.initializer:
        if init.name in names:
            init.ClearField("raw_data")
    return empty


def load(key: str | None, model: torch.nn.Module) -> onnx.ModelProto | None:
    path = _entry(key) if key else None
    if path is None or not path.is_file():
        return None
    data = path.read_bytes()
    digest, _, payload = data.partition(b"\n")
    if hashlib.sha256(payload).hexdigest().encode() != digest:
        return None  # damaged (cut short, overwritten): traced again and replaced
    try:
        empty = onnx.ModelProto.FromString(payload)
    except Exception:  # noqa: BLE001 - protobuf raises its own DecodeError or ValueError; either way unusable
        return None
    return _fill(empty, model)


def store(key: str | None, traced: onnx.ModelProto, model: torch.nn.Module) -> bool:
    path = _entry(key) if key else None
    if path is None:
        return False
    empty = _strip(traced, model)
    filled = _fill(empty, model)
    if filled is None or filled.SerializeToString() != traced.SerializeToString():
        return False  # the weights do not map one to one onto initializers: never cached
    payload = empty.SerializeToString()
    try:
        atomic_write_bytes(path, hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload)
    except OSError:
        return False  # a read-only or full cache folder costs the next export its speed, nothing else
    return True
