"""The paired comparisons of a run directory (``harness.pairs`` on its prediction folders and labels).

Two comparisons: val AP (AP40 3D moderate @0.7) on the run's val set (``data/val``, every frame listed
in ``data/val_frames.txt`` and predicted into ``predictions_valset/<tag>/``; a run without it: the SOTIF
set's val split, ``predictions_val/``) and the SOTIF headline on the SOTIF test split (``predictions/<tag>/``). Training draws are the tags
``results.json`` lists under ``draws`` (else the model's own name). The rows are cached in
``results/pairs.json`` with a key made of the bootstrap settings and the size and mtime of every label and
prediction file read, so a second report reads them back in milliseconds; a run folder without its
prediction folders (a copy) keeps the cached rows.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from harness.core.files import atomic_write_text
from harness.core.kitti import read_frames_meta, read_image_set
from harness.eval_kitti import build_eval_set
from harness.evaluate import load_folder
from harness.pairs import headline_ap, paired_comparison, val_ap
from harness.valset import FRAME_LIST, VALSET_PREDICTIONS

PAIRS_VERSION = 1  # bumped when a change alters the rows of the same predictions
CACHE = Path("results") / "pairs.json"


def model_tags(summary: dict) -> dict[str, list[str]]:
    """Each model's training-draw tags (``run --seeds K``: K of them; else the model's own name)."""
    draws = summary.get("draws") or {}
    return {m: [d["tag"] for d in draws[m]] if draws.get(m) else [m] for m in summary["models"]}


def _comparisons(run_dir: Path, tags: dict[str, list[str]]) -> list[dict]:
    """What to compare: metric, score, label root, split file, prediction folder, data description."""
    sotif = run_dir / "data" / "sotif"
    if (run_dir / FRAME_LIST).is_file() and (run_dir / VALSET_PREDICTIONS).is_dir():
        n = len(read_image_set(run_dir / FRAME_LIST))
        val = (run_dir / "data" / "val", run_dir / FRAME_LIST, VALSET_PREDICTIONS,
               f"val: {n} held-out training-generator frames")
    else:
        split = sotif / "ImageSets" / "val.txt"
        n = len(read_image_set(split)) if split.is_file() else 0
        val = (sotif, split, "predictions_val", f"SOTIF val split: {n} frames")
    test = sotif / "ImageSets" / "test.txt"
    n_test = len(read_image_set(test)) if test.is_file() else 0
    return [{"metric": "val_ap3d_moderate", "score": val_ap, "root": val[0], "split": val[1], "preds": val[2],
             "data": val[3]},
            {"metric": "headline_ap3d", "score": headline_ap, "root": sotif, "split": test, "preds": "predictions",
             "data": f"SOTIF test: {n_test} frames"}]


def _folders(run_dir: Path, comp: dict, tags: dict[str, list[str]]) -> dict[str, list[Path]]:
    """Each model's prediction folders of one comparison; models with a draw not predicted are left out."""
    out = {m: [run_dir / comp["preds"] / t for t in ts] for m, ts in tags.items()}
    return {m: fs for m, fs in out.items() if all(f.is_dir() for f in fs)}


def _units(root: Path, ids: list[str]) -> np.ndarray | None:
    """Each frame's scenario instance (``meta/frames.csv``'s ``instance_key``), or None (frames are the unit)."""
    path = root / "meta" / "frames.csv"
    if not path.is_file():
        return None
    meta = read_frames_meta(path)
    if "instance_key" not in meta.columns:
        return None
    key = meta.set_index("frame_id")["instance_key"].astype(str)
    return key.loc[[i.zfill(6) for i in ids]].to_numpy()


def _stat_key(paths: list[Path], ids: list[str]) -> list:
    """Size and mtime of every frame file of every folder in ``paths``."""
    out = []
    for folder in paths:
        for fid in ids:
            p = folder / f"{fid}.txt"
            st = p.stat() if p.is_file() else None
            out.append([st.st_size, st.st_mtime_ns] if st else None)
    return out


def _cache_key(run_dir: Path, tags: dict, n: int, seed: int) -> str:
    parts: list = [PAIRS_VERSION, n, seed]
    for comp in _comparisons(run_dir, tags):
        if not comp["split"].is_file():
            continue
        ids = read_image_set(comp["split"])
        folders = _folders(run_dir, comp, tags)
        preds = [g for fs in folders.values() for f in fs for g in (f, f / "rois")]
        parts += [str(comp["split"]), sorted(folders), _stat_key([comp["root"] / "training" / "label_2"], ids),
                  _stat_key(preds, ids)]
    return hashlib.sha256(json.dumps(parts, default=str).encode()).hexdigest()[:16]


def compute(run_dir: Path, tags: dict[str, list[str]], n: int, seed: int) -> dict[str, list[dict]]:
    """``{"rows": pair rows of both comparisons (harness.pairs.paired_comparison, n replicates each),
    "proposals": per two-stage model and comparison, the AP of its proposals alone (``rois/``) and of its
    final boxes, means over its draws}``."""
    rows, proposals = [], []
    for comp in _comparisons(run_dir, tags):
        folders = _folders(run_dir, comp, tags)
        if len(folders) < 2 or not comp["split"].is_file():
            continue
        ids = read_image_set(comp["split"])
        gt = load_folder(comp["root"] / "training" / "label_2", ids, with_score=False)
        sets = {m: [build_eval_set(gt, load_folder(f, ids, with_score=True)) for f in fs] for m, fs in folders.items()}
        rows += paired_comparison(sets, comp["score"], comp["metric"], comp["data"], _units(comp["root"], ids),
                                  n=n, seed=seed)
        everything = np.arange(len(ids))
        for m, fs in folders.items():
            if all((f / "rois").is_dir() for f in fs):
                rois = [comp["score"](build_eval_set(gt, load_folder(f / "rois", ids, with_score=True)), everything)
                        for f in fs]
                final = [comp["score"](es, everything) for es in sets[m]]
                proposals.append({"model": m, "metric": comp["metric"], "data": comp["data"], "n_draws": len(fs),
                                  "proposals": float(np.mean(rois)), "final": float(np.mean(final))})
    return {"rows": rows, "proposals": proposals}


def bootstrap_settings(summary: dict) -> tuple[int, int]:
    """(replicates, seed) of a run's bootstrap: its config's, else 200 and 0 (``RunConfig``'s defaults)."""
    cfg = summary.get("config") or {}
    return int(cfg.get("bootstrap", 200)), int(cfg.get("seed", 0))


def load_or_compute(run_dir, summary: dict) -> dict[str, list[dict]]:
    """The run's pair and proposal rows (:func:`compute`): from the cache while its key matches (or the
    predictions are gone), else computed and cached."""
    run_dir = Path(run_dir)
    n, seed = bootstrap_settings(summary)
    tags = model_tags(summary)
    cache = run_dir / CACHE
    cached = json.loads(cache.read_text()) if cache.is_file() else None
    if not (run_dir / "predictions").is_dir():
        return cached or {"rows": [], "proposals": []}
    key = _cache_key(run_dir, tags, n, seed)
    if cached and cached.get("key") == key:
        return cached
    out = {"key": key, "bootstrap": n, "seed": seed, **compute(run_dir, tags, n, seed)}
    atomic_write_text(cache, json.dumps(out, indent=1) + "\n")
    return out


def pair_tables(run_dir, summary: dict) -> dict:
    """``{"pairs": ..., "proposals": ...}`` DataFrames of the run (each only when it has rows): the
    report's ``tables/pairs.csv`` and ``tables/proposals.csv``."""
    import pandas as pd
    from harness.pairs import PAIR_COLUMNS
    got = load_or_compute(run_dir, summary)
    out = {}
    if got.get("rows"):
        out["pairs"] = pd.DataFrame(got["rows"], columns=list(PAIR_COLUMNS))
    if got.get("proposals"):
        out["proposals"] = pd.DataFrame(got["proposals"])
    return out
