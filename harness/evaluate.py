"""Evaluation driver: loads label and result folders, computes every metric, writes results JSON.

``results.json`` schema (``"schema": "sotif-bench/results/1"``; AP values in percent):

- ``kitti.<bbox|bev|3d|aos>.<0.7|0.5|official_0.5>.<R11|R40>.<easy|moderate|hard>``: the official
  KITTI protocol for Car (``0.5`` = 0.5 for every metric; ``official_0.5`` = the official
  script's second line: 0.7 for bbox, 0.5 for BEV and 3D).
- ``headline.<3d|bev>.<0.7|0.5>``: AP40 over all distances with the 2D-height, occlusion and
  truncation filters off (the SOTIF targets are far and small).
- ``distance.<3d|bev>.<0.7|0.5>.<0-30|30-50|50-80>``: AP40 by ground-truth distance, filters off.
- ``n_gt.<all|0-30|30-50|50-80>``: the Car boxes the headline and each distance bin count; an AP40
  over n boxes is at most (n - 1) / 40 (KITTI samples its recall positions among the matches).
- ``recall.<rcnn|roi>.<0.3|0.5|0.7>``: share of Car boxes whose best rotated 3D IoU with the
  given boxes exceeds the threshold (micro-averaged over frames); ``roi`` only when the
  prediction folder has ``rois/``.
- ``groups`` (with ``--group-by``): ``{"column": C, "rows": {value: {n_frames, n_car, headline,
  headline_ci95 {3d, bev: [lo, hi]} (IoU 0.7), headline_ci95_0.5 {3d: [lo, hi]}, kitti_moderate {3d, bev} (AP40 @0.7), n_gt_kitti_moderate,
  distance, n_gt, recall}}}``.
- ``groups_by``: the same for every requested column (``run`` asks for weather, time of day and
  precipitation class).
- ``pr_curve``: interpolated precision and recall at the 41 sample points of the headline 3D AP @0.7.
- ``n_frames``, ``n_car``, ``frame_ids``.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from harness.eval_kitti import DIFFICULTIES, Filter, ap_r40, build_eval_set, frame_overlaps, kitti_ap, precision_recall
from harness.kitti import KittiError, Labels, atomic_write_text, read_frames_meta, read_image_set, read_labels

SCHEMA = "sotif-bench/results/1"
# Bumped whenever a fix changes any number of the same predictions, so that a run directory
# evaluated before it evaluates again (2: BEV/3D overlaps turn boxes by -rotation_y, as the reference;
# 3: n_gt, the boxes each headline / distance / moderate AP counts; 4: the groups' interval at IoU 0.5)
EVALUATOR_VERSION = 4
ALL_DISTANCES = Filter("all")
DISTANCE_BINS = (Filter("0-30", min_distance=0, max_distance=30), Filter("30-50", min_distance=30, max_distance=50),
                 Filter("50-80", min_distance=50, max_distance=80))
RECALL_THRESHOLDS = (0.3, 0.5, 0.7)


def label_dir(path) -> Path:
    """A label folder given as itself or as a KITTI data set root."""
    path = Path(path)
    for candidate in (path / "training" / "label_2", path / "label_2", path):
        if candidate.is_dir():
            return candidate
    raise KittiError(path, "label folder not found")


def frame_ids(labels: Path, split=None) -> list[str]:
    if split is not None:
        return read_image_set(split)
    return sorted(p.stem for p in Path(labels).glob("*.txt"))


def load_folder(folder: Path, ids, with_score: bool) -> list[Labels]:
    """The label files of ``ids`` in ``folder``: ground truth (checked) or, ``with_score``, results
    (a result without scores scores 0, as in the reference; a folder of such files gets a note)."""
    out, scoreless = [], 0
    for fid in ids:
        p = Path(folder) / f"{fid}.txt"
        if not p.is_file():
            raise KittiError(p, "file not found (every frame of the split needs one, empty if nothing was found)")
        labels = read_labels(p, with_score=None)
        if not with_score:
            check_ground_truth(p, labels)
        else:
            check_results(p, labels)
        if with_score and labels.score is None:  # as the reference: a result without scores scores 0
            scoreless += len(labels) > 0
            labels.score = np.zeros(len(labels))
        out.append(labels)
    if scoreless and scoreless == sum(len(d) > 0 for d in out):
        print(f"note: {folder}: no line of its files has a score (16th field), as label files do not: is it a "
              "label folder (--labels and --predictions swapped)? Every box counts with score 0", file=sys.stderr)
    return out


_BOX_RULES = (  # (rule, test of a row, its values): every object of a result file, ground truth but DontCare
    ("box sizes (h w l) must be > 0", lambda lab: (lab.dimensions > 0).all(axis=1),
     lambda lab, i: " ".join(f"{v:g}" for v in lab.dimensions[i])),
    ("the 2D box (x1 y1 x2 y2) must have x1 <= x2 and y1 <= y2",
     lambda lab: (lab.bbox[:, 0] <= lab.bbox[:, 2]) & (lab.bbox[:, 1] <= lab.bbox[:, 3]),
     lambda lab, i: " ".join(f"{v:g}" for v in lab.bbox[i])),
)
_GT_RULES = _BOX_RULES + (  # objects but DontCare
    ("truncation must be in [0, 1]", lambda lab: (lab.truncated >= 0) & (lab.truncated <= 1),
     lambda lab, i: f"{lab.truncated[i]:g}"),
    ("occlusion must be 0, 1, 2 or 3", lambda lab: (lab.occluded >= 0) & (lab.occluded <= 3),
     lambda lab, i: f"{lab.occluded[i]}"))


def _refuse_broken_rows(path: Path, labels: Labels, rules, rows: np.ndarray) -> None:
    """KittiError naming the line of the first of ``rows`` that breaks one of ``rules``."""
    for rule, ok, values in rules:
        bad = np.flatnonzero(rows & ~ok(labels))
        if len(bad):
            raise KittiError(path, f"{rule}, got {values(labels, bad[0])}", _line_of(path, bad[0]))


def _line_of(path: Path, row: int) -> int:
    """The 1-based line of a label file that holds its ``row``-th object (blank lines skipped)."""
    return [no for no, line in enumerate(Path(path).read_text().splitlines(), start=1) if line.strip()][row]


def check_ground_truth(path: Path, labels: Labels) -> None:
    """Refuse (KittiError naming the line) a label file that is no ground truth: lines with a score
    (a result file: label and prediction folders swapped?), or an object other than DontCare with a
    size <= 0, an inverted 2D box, a truncation outside [0, 1] or an occlusion outside 0..3."""
    if not len(labels):
        return
    if labels.score is not None:
        raise KittiError(path, "has a score (16th field), as a prediction file does: is it a prediction folder "
                               "(--labels and --predictions swapped)?", _line_of(path, 0))
    _refuse_broken_rows(path, labels, _GT_RULES, np.asarray(labels.name, dtype=str) != "DontCare")


def check_results(path: Path, labels: Labels) -> None:
    """Refuse (KittiError naming the line) a result box with a size <= 0 (its IoU with anything is
    not an overlap) or an inverted 2D box (the KITTI difficulty reads its height)."""
    _refuse_broken_rows(path, labels, _BOX_RULES, np.ones(len(labels), dtype=bool))


def recall_at_iou(gt: list[Labels], boxes: list[Labels], thresholds=RECALL_THRESHOLDS, frames=None) -> dict:
    """OpenPCDet-style recall: share of Car boxes whose best rotated 3D IoU with ``boxes`` > t."""
    frames = range(len(gt)) if frames is None else frames
    hit = np.zeros(len(thresholds))
    total = 0
    for i in frames:
        cars = gt[i].select(np.asarray(gt[i].name, dtype=str) == "Car")
        total += len(cars)
        if len(cars) and len(boxes[i]):
            best = frame_overlaps(boxes[i], cars)["3d"].max(axis=0)  # (G,)
            hit += [(best > t).sum() for t in thresholds]
    return {f"{t}": (float(h / total) if total else 0.0) for t, h in zip(thresholds, hit)}


def _summary(es, frames=None) -> dict:
    """Headline AP (all distances, filters off) and distance bins for 3D and BEV at 0.7 and 0.5,
    and the number of Car boxes each counts (``n_gt``: AP40 over n boxes is at most (n - 1) / 40)."""
    head, dist = {"3d": {}, "bev": {}}, {"3d": {}, "bev": {}}
    n_gt = {}
    for metric in ("3d", "bev"):
        for thr in (0.7, 0.5):
            pr = precision_recall(es, metric, ALL_DISTANCES, thr, frames)
            head[metric][f"{thr}"] = ap_r40(pr["precision"])
            n_gt["all"] = pr["num_gt"]
            dist[metric][f"{thr}"] = {}
            for f in DISTANCE_BINS:
                pr = precision_recall(es, metric, f, thr, frames)
                dist[metric][f"{thr}"][f.name] = ap_r40(pr["precision"])
                n_gt[f.name] = pr["num_gt"]
    return {"headline": head, "distance": dist, "n_gt": n_gt}


def bootstrap_ci(es, frames, metric: str, n: int = 200, seed: int = 0, thr: float = 0.7) -> list[float]:
    """95% percentile interval of the headline AP40 over frames resampled with replacement."""
    frames = np.asarray(frames)
    if len(frames) == 0:
        return [0.0, 0.0]
    rng = np.random.default_rng(seed)
    vals = [ap_r40(precision_recall(es, metric, ALL_DISTANCES, thr, rng.choice(frames, len(frames)))["precision"])
            for _ in range(n)]
    return [float(np.percentile(vals, 2.5)), float(np.percentile(vals, 97.5))]


def _recalls(gt, preds: dict, frames=None) -> dict:
    return {stage: recall_at_iou(gt, boxes, frames=frames) for stage, boxes in preds.items()}


def _group_rows(es, gt, stage_boxes, ids, meta: pd.DataFrame, meta_path, column: str, n_boot: int,
                seed: int) -> dict:
    if column not in meta.columns or column == "frame_id":  # frame_id: one group per frame, no AP to speak of
        raise KittiError(meta_path, f"--group-by {column!r}: no such condition column "
                                    f"(columns: {', '.join(str(c) for c in meta.columns if c != 'frame_id')})")
    by_id = meta.set_index("frame_id")[column]
    keys = [i.zfill(6) for i in ids]  # the table's ids are zero-padded to KITTI's six digits
    missing = [i for i, k in zip(ids, keys) if k not in by_id.index]
    if missing:
        raise KittiError(meta_path, f"{len(missing)} frames of the split are not in the table (first: {missing[0]})")
    values = by_id.loc[keys].to_numpy()
    empty = [i for i, v in zip(ids, values) if pd.isna(v)]
    if empty:
        raise KittiError(meta_path, f"column {column!r} is empty for {len(empty)} frames of the split "
                                    f"(first: {empty[0]})")
    rows = {}
    for value in pd.unique(values):
        frames = np.flatnonzero(values == value)
        m = kitti_ap(es, filters=DIFFICULTIES[1:2], overlaps={"0.7": {"bbox": 0.7, "bev": 0.7, "3d": 0.7}}, frames=frames)
        rows[str(value)] = {
            "n_frames": int(len(frames)),
            "n_car": int(sum((np.asarray(gt[i].name, dtype=str) == "Car").sum() for i in frames)),
            **_summary(es, frames),
            "headline_ci95": {k: bootstrap_ci(es, frames, k, n_boot, seed) for k in ("3d", "bev")},
            "headline_ci95_0.5": {"3d": bootstrap_ci(es, frames, "3d", n_boot, seed, thr=0.5)},
            "kitti_moderate": {k: m[k]["0.7"]["R40"]["moderate"] for k in ("3d", "bev")},
            "n_gt_kitti_moderate": precision_recall(es, "3d", DIFFICULTIES[1], 0.7, frames)["num_gt"],
            "recall": _recalls(gt, stage_boxes, frames),
        }
    return {"column": column, "rows": rows}


def evaluate(labels, predictions, split=None, group_by=None, meta=None,
             n_bootstrap: int = 200, seed: int = 0) -> dict:
    """Every metric of one prediction folder against one label folder (see module docstring).

    ``group_by``: one meta column or a list of them; the first also fills ``groups``."""
    if n_bootstrap < 1:
        raise ValueError(f"bootstrap resamples must be at least 1, got {n_bootstrap}")
    labels, predictions = label_dir(labels), Path(predictions)
    if not predictions.is_dir():
        raise KittiError(predictions, "prediction folder not found")
    ids = frame_ids(labels, split)
    if not ids:
        raise KittiError(split or labels, "no frames to evaluate")
    gt = load_folder(labels, ids, with_score=False)
    dt = load_folder(predictions, ids, with_score=True)
    stage_boxes = {"rcnn": load_folder(predictions / "rcnn", ids, True) if (predictions / "rcnn").is_dir() else dt}
    if (predictions / "rois").is_dir():
        stage_boxes["roi"] = load_folder(predictions / "rois", ids, with_score=True)
    es = build_eval_set(gt, dt)
    curve = precision_recall(es, "3d", ALL_DISTANCES, 0.7)
    result = {"schema": SCHEMA, "n_frames": len(ids),
              "n_car": int(sum((np.asarray(g.name, dtype=str) == "Car").sum() for g in gt)),
              "kitti": kitti_ap(es), **_summary(es), "recall": _recalls(gt, stage_boxes),
              "pr_curve": {"precision": curve["precision"].tolist(), "recall": curve["recall"].tolist()},
              "frame_ids": ids}
    columns = [group_by] if isinstance(group_by, str) else list(group_by or [])
    if columns:
        if meta is None:
            raise ValueError("--group-by needs --meta meta/frames.csv")
        table = read_frames_meta(meta)
        result["groups_by"] = {c: _group_rows(es, gt, stage_boxes, ids, table, meta, c, n_bootstrap, seed)
                               for c in columns}
        result["groups"] = result["groups_by"][columns[0]]
    return result


def write_results(path, result: dict) -> Path:
    return atomic_write_text(path, json.dumps(result, indent=1, sort_keys=False) + "\n")


def format_table(result: dict) -> str:
    """A short plain-text table of the main numbers."""
    lines = ["metric      overlap  AP      easy  moderate   hard"]
    for metric in ("bbox", "bev", "3d", "aos"):
        if metric not in result["kitti"]:
            continue
        for kind in ("R11", "R40"):
            v = result["kitti"][metric]["0.7"][kind]
            lines.append(f"{metric:<11} 0.7      {kind}  {v['easy']:6.2f} {v['moderate']:8.2f} {v['hard']:7.2f}")
    h, d = result["headline"], result["distance"]
    lines.append(f"headline AP40 (all distances, no height filter) 3D@0.7 {h['3d']['0.7']:.2f}  BEV@0.7 {h['bev']['0.7']:.2f}"
                 f"  3D@0.5 {h['3d']['0.5']:.2f}")
    lines.append("distance bins 3D@0.7: " + "  ".join(f"{k} m {v:.2f}" for k, v in d["3d"]["0.7"].items()))
    for stage, rec in result["recall"].items():
        lines.append(f"recall {stage}: " + "  ".join(f"@{k} {100 * v:.1f}%" for k, v in rec.items()))
    if "groups" in result:
        g = result["groups"]
        lines.append(f"by {g['column']}: headline 3D AP40@0.7 [95% CI]")
        for value, row in g["rows"].items():
            lo, hi = row["headline_ci95"]["3d"]
            lines.append(f"  {value:<16} {row['headline']['3d']['0.7']:6.2f} [{lo:6.2f}, {hi:6.2f}]  n={row['n_frames']}")
    return "\n".join(lines)
