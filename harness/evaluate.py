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
  headline_ci95 {3d, bev: [lo, hi]} (IoU 0.7), headline_ci95_0.5 {3d: [lo, hi]}, ci_method, kitti_moderate {3d, bev} (AP40 @0.7), n_gt_kitti_moderate,
  distance, n_gt, recall}}}``. A numeric column with more than ``harness.conditions.MAX_LEVELS``
  distinct values (a swept condition) groups by quantile bins named "[lo, hi)". ``ci_method`` says
  how ``headline_ci95`` was made: "bootstrap over instances (N instances, R resamples)" when the
  data set's meta has ``instance_key`` (whole scenario instances resampled: the frames of one drive
  are not independent), else "bootstrap over frames (R resamples)".
- ``groups_by``: the same for every requested column (``run`` asks for weather, time of day and
  precipitation class).
- ``n_gt_kitti.<easy|moderate|hard>``: the Car boxes each KITTI difficulty counts (the same for every
  metric and overlap).
- ``pr_curve``: interpolated precision and recall at the 41 sample points of the headline 3D AP @0.7.
- ``pr_curve_raw``: ``{score, precision, recall}``, the same metric's precision and recall, not
  interpolated, at each score of a matched detection (highest first, at most 200 points, the first
  and the last kept): the curve runs from the best detection to the model's final recall.
- ``n_frames``, ``n_car``, ``frame_ids``.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from harness.cells import DIFFS, ap_text, binds, cap
from harness.conditions import MAX_LEVELS, condition_labels
from harness.core.files import atomic_write_text
from harness.core.kitti import KittiError, Labels, read_frames_meta, read_image_set, read_labels
from harness.eval_kitti import (DIFFICULTIES, Filter, ap_r40, build_eval_set, count_gt, frame_overlaps, kitti_ap,
                                precision_recall, score_pr_curve)

SCHEMA = "sotif-bench/results/1"
# Bumped whenever a fix changes any number of the same predictions, so that a run directory
# evaluated before it evaluates again (2: BEV/3D overlaps turn boxes by -rotation_y, as the reference;
# 3: n_gt, the boxes each headline / distance / moderate AP counts; 4: n_gt_kitti, pr_curve_raw;
# 5: the groups' interval at IoU 0.5)
EVALUATOR_VERSION = 5
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


def headline_summary(es, frames=None) -> dict:
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


def cluster_resample(frames: np.ndarray, clusters: np.ndarray, rng) -> np.ndarray:
    """``frames`` of as many clusters as there are, drawn with replacement: each drawn cluster brings all
    of its frames (the resampling unit is the cluster, e.g. a scenario instance, not the frame)."""
    keys, inverse = np.unique(clusters, return_inverse=True)
    members = [frames[inverse == i] for i in range(len(keys))]
    return np.concatenate([members[i] for i in rng.integers(0, len(keys), len(keys))])


def bootstrap_ci(es, frames, metric: str, n: int = 200, seed: int = 0, thr: float = 0.7, clusters=None) -> list[float]:
    """95% percentile interval of the headline AP40 over ``frames`` resampled with replacement, or, given
    ``clusters`` (one key per frame, e.g. its scenario instance), over whole clusters resampled."""
    frames = np.asarray(frames)
    if len(frames) == 0:
        return [0.0, 0.0]
    rng = np.random.default_rng(seed)
    draw = (lambda: rng.choice(frames, len(frames))) if clusters is None else \
        (lambda: cluster_resample(frames, np.asarray(clusters), rng))
    vals = [ap_r40(precision_recall(es, metric, ALL_DISTANCES, thr, draw())["precision"]) for _ in range(n)]
    return [float(np.percentile(vals, 2.5)), float(np.percentile(vals, 97.5))]


def ci_method(clusters, n_boot: int) -> str:
    """How an interval was made, for results.json and the report."""
    if clusters is None:
        return f"bootstrap over frames ({n_boot} resamples)"
    return f"bootstrap over instances ({len(set(clusters))} instances, {n_boot} resamples)"


def _recalls(gt, preds: dict, frames=None) -> dict:
    return {stage: recall_at_iou(gt, boxes, frames=frames) for stage, boxes in preds.items()}


def _grouping(values: np.ndarray) -> np.ndarray:
    """A numeric column with many values (a swept condition) grouped by quantile bins, any other as is
    (``harness.conditions``)."""
    series = pd.Series(values)
    if pd.api.types.is_numeric_dtype(series) and series.nunique() > MAX_LEVELS:
        return condition_labels(series).to_numpy()
    return values


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
    values = _grouping(values)
    instances = meta.set_index("frame_id")["instance_key"].loc[keys].astype(str).to_numpy() \
        if "instance_key" in meta.columns else None  # (F,) the resampling unit of the intervals
    rows = {}
    for value in pd.unique(values):
        frames = np.flatnonzero(values == value)
        clusters = None if instances is None else instances[frames]
        m = kitti_ap(es, filters=DIFFICULTIES[1:2], overlaps={"0.7": {"bbox": 0.7, "bev": 0.7, "3d": 0.7}}, frames=frames)
        rows[str(value)] = {
            "n_frames": int(len(frames)),
            "n_car": int(sum((np.asarray(gt[i].name, dtype=str) == "Car").sum() for i in frames)),
            **headline_summary(es, frames),
            "headline_ci95": {k: bootstrap_ci(es, frames, k, n_boot, seed, clusters=clusters) for k in ("3d", "bev")},
            "ci_method": ci_method(clusters, n_boot),
            "headline_ci95_0.5": {"3d": bootstrap_ci(es, frames, "3d", n_boot, seed, thr=0.5, clusters=clusters)},
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
    raw = score_pr_curve(es, "3d", ALL_DISTANCES, 0.7)
    result = {"schema": SCHEMA, "n_frames": len(ids),
              "n_car": int(sum((np.asarray(g.name, dtype=str) == "Car").sum() for g in gt)),
              "kitti": kitti_ap(es), **headline_summary(es), "recall": _recalls(gt, stage_boxes),
              "n_gt_kitti": {f.name: count_gt(es, f) for f in DIFFICULTIES},
              "pr_curve": {"precision": curve["precision"].tolist(), "recall": curve["recall"].tolist()},
              "pr_curve_raw": {k: v.tolist() for k, v in raw.items()},
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


def _short(value: float, n: int, what: str, kind: str = "R40") -> str:
    """A table cell: "no easy cars", "2.50 (<= 2.50)" under a binding cap, else "57.12"."""
    if n <= 0:
        return f"no {what}"
    return f"{value:.2f} (<= {cap(n, kind):.2f})" if binds(n, kind) else f"{value:.2f}"


def _kitti_lines(result: dict) -> list[str]:
    n = result["n_gt_kitti"]
    lines = [f"{'KITTI protocol, Car, IoU 0.7':<30}" + "".join(f"{d:<18}" for d in DIFFS),
             f"{'  cars counted':<30}" + "".join(f"{n[d]:<18}" for d in DIFFS)]
    for metric in ("bbox", "bev", "3d", "aos"):
        for kind in ("R11", "R40") if metric in result["kitti"] else ():
            v = result["kitti"][metric]["0.7"][kind]
            lines.append(f"{'  ' + metric + ' AP' + kind[1:]:<30}"
                         + "".join(f"{_short(v[d], n[d], d + ' cars', kind):<18}" for d in DIFFS))
    return [line.rstrip() for line in lines]


def format_table(result: dict) -> str:
    """A short plain-text table of the main numbers, each AP beside the Car boxes it counts and, when
    KITTI's sampling caps it below 100 (``harness.cells``), that cap."""
    h, d, n = result["headline"], result["distance"], result["n_gt"]
    lines = _kitti_lines(result)
    heads = (("3D@0.7", "3d", "0.7"), ("BEV@0.7", "bev", "0.7"), ("3D@0.5", "3d", "0.5"))
    lines.append(f"headline AP40 (all distances, no height filter, {n['all']} cars): "
                 + "  ".join(f"{name} {_short(h[m][t], n['all'], 'cars')}" for name, m, t in heads))
    lines.append("distance bins 3D@0.7: "
                 + "  ".join(f"{k} m {ap_text(v, n[k], 'cars')}" for k, v in d["3d"]["0.7"].items()))
    for stage, rec in result["recall"].items():
        lines.append(f"recall {stage}: " + "  ".join(f"@{k} {100 * v:.1f}%" for k, v in rec.items()))
    if "groups" in result:
        g = result["groups"]
        lines.append(f"by {g['column']}: headline 3D AP40@0.7 [95% CI]")
        for value, row in g["rows"].items():
            lo, hi = row["headline_ci95"]["3d"]
            at_most = f", at most {cap(row['n_car']):.2f}" if binds(row["n_car"]) else ""
            lines.append(f"  {value:<16} {row['headline']['3d']['0.7']:6.2f} [{lo:6.2f}, {hi:6.2f}]  "
                         f"{row['n_frames']} frames, {row['n_car']} cars{at_most}")
    groups = result.get("groups", {}).get("rows", {}).values()
    counts = [*result["n_gt_kitti"].values(), *n.values(), *(r["n_car"] for r in groups)]
    if any(binds(c) for c in counts):
        lines += ["note: KITTI samples its recall positions among the matches, so over n <= 40 cars AP40 is at most "
                  "(n - 1) / 40 and AP11 at most ceil(n / 4) / 11:",
                  "      a value marked <= is held down by the number of cars, not only by the detector; "
                  "\"no ... cars\": that AP counts no car and means nothing"]
    return "\n".join(lines)
