"""Imported models in a run (``run --checkpoints DIR``): published weights evaluated beside trained ones.

A checkpoint that ``sotif-bench import`` wrote (a ``kitti``-profile checkpoint carrying ``published``:
source, config file, file name, SHA-256, classes) becomes a model of the run under the tag
``<model>_<source>`` (``second_openpcdet``, ``dv_second_mmdet3d``; the source's suffix keeps a tag apart
from every trained model's name and draw). It is not trained: the stage ``import_<tag>``
(``harness.model_stages``) copies it to ``models/<tag>/checkpoint.pt``, where a trained model keeps its
checkpoint, and from there the export, prediction, evaluation and runtime stages are the trained models' own. It has one draw whatever
``--seeds`` (its weights are given, not drawn). In ``results.json`` its model entry holds ``published``
(the provenance, from its ONNX file's ``sotif.published``) and ``train`` null; the report marks it
(``weights``: published, and the provenance under the models table).

Every file is read before any stage runs; bad input is a ValueError naming the file and the problem
(exit 2): no such file or folder, a folder without a ``.pt`` file, a file that is no checkpoint or whose
weights do not fit its network, a checkpoint that ``import`` did not write, two files of one tag.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

PROVENANCE_KEYS = ("source", "config", "file", "sha256", "classes")  # what import writes (harness.import_weights)


def checkpoint_files(path) -> list[Path]:
    """The checkpoint files of ``--checkpoints``: the file itself, or the ``.pt`` files of a folder."""
    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.glob("*.pt") if p.is_file() and not p.name.startswith("."))
        if not files:
            raise ValueError(f"--checkpoints {path}: the folder holds no .pt file (the checkpoints `sotif-bench "
                             "import` writes)")
        return files
    if not path.is_file():
        raise ValueError(f"--checkpoints {path}: no such file or folder")
    return [path]


def read_published(path: Path) -> tuple[str, dict]:
    """(tag, provenance) of a checkpoint written by ``import``; a ValueError naming the file and the problem."""
    from harness.import_weights import SOURCES
    from models.zoo import load_checkpoint
    _, meta = load_checkpoint(path)  # CheckpointError (a ValueError): not a checkpoint, unreadable, misfit weights
    prov = meta.get("published")
    if prov is None:
        raise ValueError(f"{path}: a {meta['model']}/{meta['profile']} checkpoint without published provenance, "
                         "not one `sotif-bench import` wrote (a model trained here enters a run through --models)")
    lacking = [k for k in PROVENANCE_KEYS if not isinstance(prov, dict) or not prov.get(k)]
    if lacking or prov["source"] not in SOURCES or meta["profile"] != "kitti":
        raise ValueError(f"{path}: its published provenance is not what `sotif-bench import` writes (a kitti-profile "
                         f"checkpoint with {', '.join(PROVENANCE_KEYS)}; source one of {', '.join(SOURCES)})")
    return f"{meta['model']}_{prov['source']}", prov


def add(cfg, names: list[str], checkpoints) -> tuple:
    """(``cfg`` with ``published``, ``names`` and the imported models' tags): the run's models with the
    checkpoints of ``checkpoints`` (a file, a folder, or None) added."""
    if checkpoints is None:
        if not names:
            raise ValueError("--models none: no model to run; give --checkpoints DIR (imported checkpoints) or "
                             "name models")
        return cfg, names
    tags: dict[str, Path] = {}
    for path in checkpoint_files(checkpoints):
        tag, _ = read_published(path)
        if tag in tags:
            raise ValueError(f"{path}: its model tag {tag} is also {tags[tag]}'s; one run holds one model of a "
                             "tag (run the other into another --out)")
        tags[tag] = path
    return replace(cfg, published=tuple((t, str(p.resolve())) for t, p in tags.items())), names + list(tags)


def source(cfg, tag: str) -> Path | None:
    """The imported checkpoint of an imported model of the run; None for a trained one."""
    return next((Path(p) for t, p in cfg.published if t == tag), None)


def trained(cfg, names: list[str]) -> list[str]:
    """The models of ``names`` the run trains."""
    return [n for n in names if source(cfg, n) is None]


def draws(cfg, name: str) -> int:
    """Training draws of a model: one for an imported model."""
    return 1 if source(cfg, name) else cfg.seeds


def mark(cfg, run_dir: Path, name: str, entry: dict) -> dict:
    """A model's ``results.json`` entry; an imported model's with its provenance and no training."""
    if source(cfg, name) is None:
        return entry
    from harness.infer import check_contract
    meta = check_contract(run_dir / entry["onnx"]).metadata
    return {**entry, "published": json.loads(meta["sotif.published"]), "train": None}


def weights(entry: dict) -> str:
    """``published`` for a model entry of ``results.json`` with published weights, else ``trained``."""
    return "published" if entry.get("published") else "trained"


def published_note(summary: dict) -> str:
    """The report's line under the models table: where each imported model's weights come from ("" if none)."""
    rows = [f"{name}: {p.get('config')}, file {p.get('file')} "
            f"(SHA-256 {str(p.get('sha256'))[:12]}...; classes {', '.join(p.get('classes') or [])}, its Car boxes "
            "scored)" for name, m in summary["models"].items() if isinstance(p := m.get("published"), dict)]
    return ("Published weights, imported and not trained in this run (`run --checkpoints`): " + "; ".join(rows) + "."
            if rows else "")
