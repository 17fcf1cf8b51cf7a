"""SOTIF view: when does each detector first find the slow car in the ego lane after the cut-out?

The SOTIF scenario (simulator.scenario): a fast car ahead of the ego changes lane and reveals a
slow car in the ego lane. Per weather preset, this module finds the first test frame at or after
the lane change in which a detector finds the slow car, and compares the distance left at that
moment with the distance the ego needs to brake to the slow car's speed:

    d_stop = dv * T_REACT_S + dv^2 / (2 * DECEL_MPS2) + MARGIN_M,  dv = ego speed - slow car speed

The simulated ego's ACC reacts to the ground truth, so it brakes before any detector could tell it
to. The verdict therefore takes distance d0 and closing speed dv0 at the first frame after the lane
change and assumes the ego holds dv0 until the detection at time t: it passes when
d0 - dv0 * (t - t0) >= d_stop(dv0).

A frame counts as a detection when a predicted box with score >= the model's operating threshold
has BEV IoU >= ``IOU_BEV_MIN`` with the slow car's ground-truth box (row ``slow_car_label_index``
of the frame's label_2 file). The operating threshold is the F1-optimal score threshold at BEV
IoU 0.5 over all Car boxes of the "val" split (``FALLBACK_THRESHOLD`` when val is empty or has no
prediction files). Distances are gaps from the ego's front bumper to the slow car's rear face
(BEV range of the box centre minus half its length, minus ``LIDAR_TO_FRONT_M``: the simulated
LiDAR sits above the centre of the ego), metres. Pure functions first, then the driver ``sotif_view``.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from harness.core.boxes import iou_bev
from harness.core.braking import DECEL_MPS2, EGO_DIMS, MARGIN_M, T_REACT_S, stopping_distance
from harness.core.kitti import KittiError, Labels, frame_path, read_calib, read_frames_meta, read_image_set, read_labels

LIDAR_TO_FRONT_M = EGO_DIMS[0] / 2  # m, the ego's front bumper ahead of its roof LiDAR (above its centre)
IOU_BEV_MIN = 0.5
FALLBACK_THRESHOLD = 0.3
META_COLUMNS = ("frame_id", "weather", "scenario_time_s", "lane_change_time_s", "slow_car_label_index",
                "ego_speed_mps", "slow_car_speed_mps")


# ----------------------------------------------------------------------------- pure functions
def greedy_match(boxes: np.ndarray, scores: np.ndarray, gt: np.ndarray, iou_min: float = IOU_BEV_MIN,
                 overlap=iou_bev) -> np.ndarray:
    """(D,) bool: detection i (LiDAR box (D, 7)) matched a ground-truth box (G, 7) at IoU >= iou_min, the IoU
    given by ``overlap`` ((D, 7), (G, 7) -> (D, G); BEV by default, ``harness.core.boxes.iou_3d`` for 3D).

    Detections are taken by descending score; each takes its best still-free ground truth. Since
    higher scores go first, keeping only detections above any threshold leaves their matches unchanged.
    """
    matched = np.zeros(len(boxes), dtype=bool)
    if len(boxes) == 0 or len(gt) == 0:
        return matched
    iou = overlap(boxes, gt)  # (D, G)
    free = np.ones(len(gt), dtype=bool)
    for i in np.argsort(-np.asarray(scores), kind="stable"):
        cand = np.where(free, iou[i], -1.0)
        j = int(np.argmax(cand))
        if cand[j] >= iou_min:
            matched[i], free[j] = True, False
    return matched


def f1_optimal_threshold(scores: np.ndarray, matched: np.ndarray, n_gt: int) -> tuple[float | None, float]:
    """(threshold, F1) maximising F1 over score thresholds; ties go to the higher threshold.

    ``scores``/``matched`` are the detections of all frames (matched by ``greedy_match``); a
    detection is kept when its score >= threshold. Returns (None, 0.0) when no threshold has F1 > 0.
    """
    scores, matched = np.asarray(scores, dtype=np.float64), np.asarray(matched, dtype=bool)
    if n_gt <= 0 or scores.size == 0:
        return None, 0.0
    order = np.argsort(-scores, kind="stable")
    s, tp = scores[order], np.cumsum(matched[order])  # (D,) detections kept down to position i
    last = np.r_[s[1:] != s[:-1], True]  # only the last of equal scores is a valid cut
    n_kept = np.arange(1, len(s) + 1)
    f1 = 2.0 * tp / (n_kept + n_gt)  # 2TP / (2TP + FP + FN) with TP + FP = kept, TP + FN = n_gt
    f1 = np.where(last, f1, -1.0)
    best = int(np.argmax(f1))  # first maximum = highest threshold among ties
    if f1[best] <= 0:
        return None, 0.0
    return float(s[best]), float(f1[best])


def first_hit(hits) -> int | None:
    """Index of the first True in ``hits`` (frames in time order), or None."""
    idx = np.flatnonzero(np.asarray(hits, dtype=bool))
    return int(idx[0]) if idx.size else None


def slow_car_detected(pred_boxes: np.ndarray, pred_scores: np.ndarray, slow_box: np.ndarray, threshold: float,
                      iou_min: float = IOU_BEV_MIN) -> bool:
    """Some prediction with score >= threshold overlaps the slow car's box (7,) at BEV IoU >= iou_min."""
    keep = np.asarray(pred_scores) >= threshold
    if not keep.any():
        return False
    return bool((iou_bev(np.asarray(pred_boxes)[keep], np.asarray(slow_box).reshape(1, 7))[:, 0] >= iou_min).any())


def rear_distance(box: np.ndarray, lidar_to_front: float = LIDAR_TO_FRONT_M) -> float:
    """Metres from the ego's front bumper to the rear face of a box ahead: BEV range of its centre
    minus l / 2, minus the bumper's distance ahead of the LiDAR."""
    return float(math.hypot(box[0], box[1]) - box[3] / 2.0 - lidar_to_front)


# ----------------------------------------------------------------------------- loaders
def split_ids(data_dir: Path, split: str) -> list[str]:
    """The frame ids of ``ImageSets/<split>.txt``; none when the data set has no such split."""
    path = data_dir / "ImageSets" / f"{split}.txt"
    return read_image_set(path) if path.is_file() else []


def lidar_labels(data_dir: Path, folder: Path, fid: str, with_score: bool) -> tuple[np.ndarray, np.ndarray, Labels]:
    """(K, 7) LiDAR boxes, (K,) scores (ones for ground truth) and the labels of one label/result file."""
    labels = read_labels(folder / f"{fid}.txt", with_score=with_score or None)
    calib = read_calib(frame_path(data_dir, "calib", fid))
    boxes = labels.to_lidar(calib) if len(labels) else np.zeros((0, 7), np.float32)
    scores = labels.score if labels.score is not None else np.ones(len(labels))
    return boxes, scores, labels


def load_meta(data_dir) -> pd.DataFrame:
    """The data set's meta/frames.csv with the SOTIF columns checked (ValueError naming the file)."""
    path = Path(data_dir) / "meta" / "frames.csv"
    meta = read_frames_meta(path)
    missing = [c for c in META_COLUMNS if c not in meta.columns]
    if missing:
        raise KittiError(path, f"no SOTIF scenario columns {', '.join(missing)} (needed for the SOTIF view)")
    return meta


def operating_threshold(data_dir, predictions_dir, split: str = "val") -> tuple[float, str]:
    """(threshold, source): the F1-optimal score threshold at BEV IoU 0.5 on ``split`` (a split name of
    ``data_dir`` or an ImageSets file listing frame ids), or the fallback."""
    data_dir, predictions_dir = Path(data_dir), Path(predictions_dir)
    ids = read_image_set(split) if Path(split).suffix == ".txt" else split_ids(data_dir, split)
    split = f"{Path(split).name} ({len(ids)} frames)" if Path(split).suffix == ".txt" else split
    present = [fid for fid in ids if (predictions_dir / f"{fid}.txt").is_file()]
    if not present:
        return FALLBACK_THRESHOLD, f"fallback ({split} split empty or not predicted)"
    if len(present) != len(ids):
        missing = next(fid for fid in ids if fid not in set(present))
        raise KittiError(predictions_dir / f"{missing}.txt", f"file not found ({len(ids) - len(present)} of the "
                                                           f"{len(ids)} {split} frames lack predictions)")
    scores, matched, n_gt = [], [], 0
    label_dir = frame_path(data_dir, "label_2", "0").parent
    for fid in ids:
        gt, _, gt_labels = lidar_labels(data_dir, label_dir, fid, with_score=False)
        gt = gt[np.asarray(gt_labels.name, dtype=str) == "Car"] if len(gt) else gt
        boxes, s, _ = lidar_labels(data_dir, predictions_dir, fid, with_score=True)
        scores.append(s)
        matched.append(greedy_match(boxes, s, gt))
        n_gt += len(gt)
    thr, f1 = f1_optimal_threshold(np.concatenate(scores), np.concatenate(matched), n_gt)
    if thr is None:
        return FALLBACK_THRESHOLD, f"fallback (no detection matches a car on {split})"
    return thr, f"F1-optimal on {split} (F1 {f1:.3f})"


# ----------------------------------------------------------------------------- driver
def gap_without_braking(d0: float, closing_speed_mps: float, dt_s: float) -> float:
    """Distance left after ``dt_s`` seconds if the ego keeps closing in at the given speed from ``d0``."""
    return d0 - max(closing_speed_mps, 0.0) * dt_s


def slow_car_track(data_dir: Path, predictions_dir: Path, after: pd.DataFrame, threshold: float):
    """Per frame (time order): the slow car's GT box and whether the model detected it."""
    label_dir = frame_path(data_dir, "label_2", "0").parent
    hits, slow_boxes = [], []
    for fr in after.itertuples(index=False):
        gt, _, _ = lidar_labels(data_dir, label_dir, fr.frame_id, with_score=False)
        k = int(fr.slow_car_label_index)
        if k >= len(gt):
            raise KittiError(label_dir / f"{fr.frame_id}.txt", f"slow_car_label_index {k} but only {len(gt)} objects")
        boxes, scores, _ = lidar_labels(data_dir, predictions_dir, fr.frame_id, with_score=True)
        hits.append(slow_car_detected(boxes, scores, gt[k], threshold))
        slow_boxes.append(gt[k])
    return hits, slow_boxes


def _weather_row(data_dir: Path, predictions_dir: Path, frames: pd.DataFrame, threshold: float) -> dict:
    """First detection of the slow car after the lane change in one weather's frames (time order).

    The simulated ego already brakes for the slow car (its ACC sees the ground truth), so the verdict
    uses the situation at the first frame after the lane change: distance d0 and closing speed dv0 there,
    the ego holding dv0 until the detection (``distance_if_no_braking_m``) against ``stopping_distance(dv0)``.
    ``distance_m`` is the distance measured at the detection frame.
    """
    t_lc = float(frames["lane_change_time_s"].iloc[0]) if len(frames) else float("nan")
    after = frames[(frames["scenario_time_s"] >= t_lc - 1e-6) & (frames["slow_car_label_index"] >= 0)]
    row = {"lane_change_time_s": None if math.isnan(t_lc) else t_lc, "n_frames_after_lane_change": int(len(after)),
           "detected": False, "frame_id": None, "distance_m": None, "distance_if_no_braking_m": None,
           "time_after_lane_change_s": None, "distance_at_lane_change_m": None, "closing_speed_mps": None,
           "stopping_distance_m": None, "pass": None}
    if math.isnan(t_lc) or after.empty:
        return row
    hits, slow_boxes = slow_car_track(data_dir, predictions_dir, after, threshold)
    ref = after.iloc[0]
    dv0, d0, t0 = float(ref["ego_speed_mps"] - ref["slow_car_speed_mps"]), rear_distance(slow_boxes[0]), float(ref["scenario_time_s"])
    row.update(distance_at_lane_change_m=d0, closing_speed_mps=dv0, stopping_distance_m=stopping_distance(dv0), **{"pass": False})
    i = first_hit(hits)
    if i is None:
        return row
    at = after.iloc[i]
    t = float(at["scenario_time_s"])
    row.update(detected=True, frame_id=str(at["frame_id"]), distance_m=rear_distance(slow_boxes[i]),
               distance_if_no_braking_m=gap_without_braking(d0, dv0, t - t0), time_after_lane_change_s=t - t_lc)
    row["pass"] = bool(row["distance_if_no_braking_m"] >= row["stopping_distance_m"])
    return row


def sotif_view(data_dir, predictions_dir, split: str = "test", threshold: float | None = None,
               val_predictions_dir=None, threshold_source: str = "given") -> dict:
    """Per weather preset: first detection of the slow car after the lane change vs the stopping distance.

    ``{weather: {threshold, threshold_source, lane_change_time_s, n_frames_after_lane_change, detected,
    frame_id, distance_m, distance_if_no_braking_m, time_after_lane_change_s, distance_at_lane_change_m,
    closing_speed_mps, stopping_distance_m, pass}}`` (see ``_weather_row``); never detected -> ``pass``
    False; no lane change in the data -> ``pass`` None.
    ``val_predictions_dir`` (default ``predictions_dir``) holds the val split's result files.
    """
    data_dir, predictions_dir = Path(data_dir), Path(predictions_dir)
    if not predictions_dir.is_dir():
        raise KittiError(predictions_dir, "prediction folder not found")
    meta = load_meta(data_dir)
    if threshold is None:
        threshold, source = operating_threshold(data_dir, val_predictions_dir or predictions_dir)
    else:
        source = threshold_source
    ids = split_ids(data_dir, split)
    if not ids:
        raise KittiError(data_dir / "ImageSets" / f"{split}.txt", "no frames in the split")
    frames = meta[meta["frame_id"].isin(set(ids))]
    weathers = pd.unique(frames["weather"])  # data set order
    frames = frames.sort_values("scenario_time_s", kind="stable")
    out = {}
    for weather in weathers:
        row = _weather_row(data_dir, predictions_dir, frames[frames["weather"] == weather], threshold)
        out[str(weather)] = {"threshold": float(threshold), "threshold_source": source, **row}
    return out


def constants() -> dict:
    """The documented constants, for reports."""
    return {"t_react_s": T_REACT_S, "decel_mps2": DECEL_MPS2, "margin_m": MARGIN_M, "iou_bev_min": IOU_BEV_MIN,
            "fallback_threshold": FALLBACK_THRESHOLD}
