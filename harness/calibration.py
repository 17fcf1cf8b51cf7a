"""Score calibration per weather class: does a detector's score say how often its box is right?

Every predicted box of a test frame is *correct* when it is matched to a ground-truth Car box at
3D IoU >= t (t = 0.7 and 0.5; greedy by descending score, each ground truth matched once). Scores
go into ``N_BINS`` equal-width bins over [0, 1] (a score of 1 in the last bin); a bin's confidence
is its mean score and its accuracy the share of its boxes that are correct. The expected
calibration error is ECE = sum_b (n_b / N) * |accuracy_b - confidence_b| over the non-empty bins
(Guo et al. 2017, "On Calibration of Modern Neural Networks"). Grouped by ``precipitation_class``
(dry / wet / rain) and over all frames. Pure functions first, then the driver.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from harness import sotif
from harness.core.boxes import iou_3d
from harness.core.kitti import KittiError, frame_path

N_BINS = 10
IOUS = (0.7, 0.5)
GROUP_COLUMN = "precipitation_class"


def match_3d(boxes: np.ndarray, scores: np.ndarray, gt: np.ndarray, iou_min: float) -> np.ndarray:
    """(D,) bool: detection i (LiDAR box (D, 7)) matched a ground-truth box (G, 7) at 3D IoU >= iou_min,
    greedy by descending score, each ground truth taken once (``harness.sotif.greedy_match`` in 3D)."""
    return sotif.greedy_match(boxes, scores, gt, iou_min, overlap=iou_3d)


def reliability(scores, correct, n_bins: int = N_BINS) -> dict:
    """``{ece, n, bins: {count, confidence, accuracy}}`` (per-bin lists, None for an empty bin)."""
    s, c = np.asarray(scores, dtype=np.float64), np.asarray(correct, dtype=np.float64)
    b = np.clip((s * n_bins).astype(np.int64), 0, n_bins - 1)  # (D,) bin of each score
    count = np.bincount(b, minlength=n_bins)
    conf = np.bincount(b, weights=s, minlength=n_bins).astype(np.float64)  # (n_bins,) sums, then means
    acc = np.bincount(b, weights=c, minlength=n_bins).astype(np.float64)
    full = count > 0
    conf[full] /= count[full]
    acc[full] /= count[full]
    ece = float((count[full] / s.size * np.abs(acc[full] - conf[full])).sum()) if s.size else None
    opt = lambda v: [float(x) if f else None for x, f in zip(v, full)]
    return {"ece": ece, "n": int(s.size), "bins": {"count": count.tolist(), "confidence": opt(conf),
                                                   "accuracy": opt(acc)}}


def calibration_view(data_dir, predictions_dir, split: str = "test", ious=IOUS, n_bins: int = N_BINS) -> dict:
    """``{"<iou>": {"all" | <precipitation class>: reliability(...)}}`` over the test frames."""
    data_dir, predictions_dir = Path(data_dir), Path(predictions_dir)
    meta = sotif.load_meta(data_dir)
    ids = sotif.split_ids(data_dir, split)
    if not ids:
        raise KittiError(data_dir / "ImageSets" / f"{split}.txt", "no frames in the split")
    group = meta.set_index("frame_id")[GROUP_COLUMN] if GROUP_COLUMN in meta.columns else None
    label_dir = frame_path(data_dir, "label_2", "0").parent
    scores, correct, classes = [], {t: [] for t in ious}, []
    for fid in ids:
        gt, _, gt_labels = sotif.lidar_labels(data_dir, label_dir, fid, with_score=False)
        gt = gt[np.asarray(gt_labels.name, dtype=str) == "Car"] if len(gt) else gt
        boxes, s, _ = sotif.lidar_labels(data_dir, predictions_dir, fid, with_score=True)
        scores.append(np.asarray(s, dtype=np.float64))
        for t in ious:
            correct[t].append(match_3d(boxes, s, gt, t))
        classes += [str(group.get(fid, "?")) if group is not None else "all"] * len(s)
    s_all = np.concatenate(scores) if scores else np.zeros(0)
    cls = np.asarray(classes, dtype=object)
    out = {}
    for t in ious:
        c_all = np.concatenate(correct[t]) if correct[t] else np.zeros(0, bool)
        out[f"{t}"] = {"all": reliability(s_all, c_all, n_bins),
                       **{str(g): reliability(s_all[cls == g], c_all[cls == g], n_bins)
                          for g in dict.fromkeys(cls.tolist()) if group is not None}}
    return out
