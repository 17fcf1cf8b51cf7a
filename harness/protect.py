"""Outputs that must not replace what they should not: an output path that is one of the command's
inputs (or lies inside an input folder), or an existing file of another kind, is refused with a
``ValueError`` naming the paths (exit 2 from the CLI) unless ``--force`` is given.

``train`` guards its checkpoint itself (``harness.train``): a checkpoint records its model, and a
training of another model does not replace it.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Callable

_RESULTS_HEAD = re.compile(rb'^\s*\{\s*"schema"\s*:\s*"sotif-bench/results/')


def _inside(path: Path, given: Path) -> bool:
    """``path`` is ``given`` or, when ``given`` is a folder, lies somewhere below it (links resolved)."""
    path, given = path.resolve(), given.resolve()
    return path == given or (given.is_dir() and given in path.parents)


def refuse_overwrite(out, kind: str, inputs: dict | None = None, foreign: Callable[[Path], str | None] | None = None,
                     force: bool = False) -> None:
    """Refuse to write ``kind`` (e.g. "an ONNX model") to ``out`` when ``out`` is one of ``inputs``
    ({flag: path or None}) or lies inside an input folder, or when it exists and ``foreign(out)``
    describes it as something else. ``force``: no check."""
    if force:
        return
    out = Path(out)
    for flag, given in (inputs or {}).items():
        if given is not None and _inside(out, Path(given)):
            where = "is inside" if Path(given).is_dir() else "is"
            raise ValueError(f"{out}: {where} the {flag} input {given}; writing {kind} there would replace an "
                             "input (pass --force to write it anyway, or choose another output path)")
    found = foreign(out) if foreign is not None and out.is_file() else None
    if found:
        raise ValueError(f"{out}: exists and is {found}, not {kind}; refusing to replace it "
                         "(pass --force to replace it, or choose another output path)")


def _looks_like(head: bytes) -> str:
    """What a file of another kind looks like, from its first bytes."""
    if head.startswith(b"PK\x03\x04"):
        return "a zip archive (a PyTorch checkpoint?)"
    try:
        first = head.decode("utf-8").split("\n", 1)[0].strip()
    except UnicodeDecodeError:
        return "a binary file of another kind"
    words = first.split()
    kind = "a KITTI label or result file" if len(words) in (15, 16) and words[0][:1].isalpha() else "a text file"
    return f"{kind} (line 1: {first[:60]!r})"


def _head(path: Path) -> bytes:
    with open(path, "rb") as f:
        return f.read(4096)


def foreign_results(path: Path) -> str | None:
    """None for a results file ``evaluate`` wrote, else what the file looks like."""
    head = _head(path)
    return None if _RESULTS_HEAD.match(head) else _looks_like(head)


def foreign_onnx(path: Path) -> str | None:
    """None for an ONNX model, else what the file looks like."""
    import onnx
    try:
        model = onnx.load(str(path), load_external_data=False)
        if model.ir_version > 0 and len(model.graph.node) > 0:
            return None
    except Exception:  # noqa: BLE001 - protobuf raises several decode errors for a file of another kind
        pass
    return _looks_like(_head(path))
