"""A scenario set's frames as the SOTIF verdict reads them, the reference's view of each, and a detector's hits.

- ``scenario_frames``: the split's frames at or after each instance's lane change in which the slow vehicle has
  a label row (meta/frames.csv's ``slow_car_label_index``; a DontCare row keeps the vehicle's 3D box), per
  instance in time order, with the instance's body, paint and conditions. A set without the scenario columns,
  or with a body or sweep axis this code does not know, is refused naming the file and the value.
- ``reference_frames``: per frame the slow vehicle's box, the other label boxes (every row is a vehicle: the
  occluders and the objects a phantom must miss), the footprint shares seen from the sensor
  (``harness.core.visibility``) and the ego lane's curvature (``harness.inpath.lane_curvature``).
- ``detector_frames``: per frame whether a detector's result file holds an in-path hit on the slow vehicle
  (``harness.inpath``), a box of BEV IoU >= 0.5 with it (box quality) and how many phantom in-path boxes.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from harness import inpath
from harness.core import visibility
from harness.core.boxes import iou_bev
from harness.core.kitti import KittiError, frame_path, read_calib, read_image_set, read_labels
from harness.sotif import load_meta
from simulator.scenario import SotifConfig
from simulator.vehicles import BODY_TYPES

AXES = ("preset", "rain", "fog", "water", "reflectance")  # meta/frames.csv's sweep_axis values (bounds sets: reflectance)
LEARNED = "Car"  # the class the detectors are trained on; other bodies are reported apart
IOU_BEV_MIN = 0.5


def body_class(body: str) -> str:
    """"car" for a body labelled Car (the class the detectors learned), else "outside the learned classes"."""
    label = BODY_TYPES[body].label if body in BODY_TYPES else str(body).capitalize()
    return "car" if label == LEARNED else "outside the learned classes"


def _check_values(path: Path, frames: pd.DataFrame) -> None:
    """KittiError naming the value: a slow-vehicle body or a sweep axis this code does not know."""
    for column, known in (("sc_slow_body", tuple(BODY_TYPES)), ("sweep_axis", AXES)):
        if column not in frames.columns:
            continue
        bad = frames.loc[~frames[column].isin(known), ["frame_id", column]]
        if len(bad):
            fid, value = bad.iloc[0]
            what = "body" if column == "sc_slow_body" else "sweep axis"
            raise KittiError(path, f"unknown {what} {value!r} in column {column} (frame {fid}); known: {', '.join(known)}")


def _study_vehicle(data_dir: Path) -> dict:
    """The slow vehicle's body and paint of a set of the study's protocol (no sc_* columns): its
    meta/dataset.json's scenario config, else the study's silver sedan."""
    body, paint = SotifConfig().slow_body[0], SotifConfig().slow_body[2]
    try:
        config = json.loads((data_dir / "meta" / "dataset.json").read_text())["config"]["sotif"]["slow_body"]
        body, paint = str(config[0]), str(config[2])
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        pass
    return {"sc_slow_body": body, "sc_slow_paint": paint}


def scenario_frames(data_dir, split: str = "test") -> pd.DataFrame:
    """The frames the verdict judges (module docstring), sorted by instance and time; columns of meta/frames.csv
    plus ``instance_key`` and ``t_s`` (seconds after the instance's lane change)."""
    data_dir = Path(data_dir)
    meta = load_meta(data_dir)
    path = data_dir / "ImageSets" / f"{split}.txt"
    ids = set(read_image_set(path)) if path.is_file() else set()
    if not ids:
        raise KittiError(path, "no frames in the split")
    frames = meta[meta["frame_id"].isin(ids)].copy()
    if "sc_slow_body" not in frames.columns:
        frames = frames.assign(**_study_vehicle(data_dir))
    _check_values(data_dir / "meta" / "frames.csv", frames)
    if "instance_key" not in frames.columns:  # the study's protocol: one instance per weather
        frames["instance_key"] = frames["weather"].astype(str)
    frames["t_s"] = (frames["scenario_time_s"] - frames["lane_change_time_s"]).round(3)
    keep = (frames["t_s"] >= -1e-6) & (frames["slow_car_label_index"] >= 0)
    order = {k: i for i, k in enumerate(pd.unique(frames["instance_key"]))}  # data set order
    frames = frames[keep].assign(_order=lambda f: f["instance_key"].map(order))
    return frames.sort_values(["_order", "t_s"], kind="stable").drop(columns="_order").reset_index(drop=True)


def lidar_boxes(data_dir: Path, path: Path, fid: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, 7) LiDAR boxes, (K,) scores (1 where the file has none) and (K,) class names of a label or result
    file (an absent file: no boxes)."""
    if not path.is_file():
        return np.zeros((0, 7)), np.zeros(0), np.zeros(0, dtype=str)
    labels = read_labels(path)
    if not len(labels):
        return np.zeros((0, 7)), np.zeros(0), np.zeros(0, dtype=str)
    boxes = labels.to_lidar(read_calib(frame_path(data_dir, "calib", fid))).astype(np.float64)
    scores = labels.score if labels.score is not None else np.ones(len(labels))
    return boxes, np.asarray(scores, dtype=np.float64), np.asarray(labels.name, dtype=str)


@dataclass
class Reference:
    """A scenario set's judged frames (``frames``, one row each, with the reference's columns ``unoccluded``,
    ``in_range``, ``visible``, ``perceivable``, ``curvature``, ``rear_m``), the slow vehicle's box per frame
    (F, 7) and the other label boxes per frame."""

    data_dir: Path
    frames: pd.DataFrame
    slow: np.ndarray
    others: list


def reference_frames(data_dir, split: str = "test", visible_min: float = visibility.VISIBLE_MIN) -> Reference:
    """The reference's view of every judged frame of ``split`` (module docstring)."""
    data_dir = Path(data_dir)
    frames = scenario_frames(data_dir, split)
    label_dir = frame_path(data_dir, "label_2", "0").parent
    slow, others, rows = [], [], []
    offsets = frames["sc_lateral_offset_m"].fillna(0.0) if "sc_lateral_offset_m" in frames else pd.Series(0.0, frames.index)
    for fr, offset in zip(frames.itertuples(index=False), offsets):
        boxes, _, _ = lidar_boxes(data_dir, label_dir / f"{fr.frame_id}.txt", fr.frame_id)
        k = int(fr.slow_car_label_index)
        if k >= len(boxes):
            raise KittiError(label_dir / f"{fr.frame_id}.txt", f"slow_car_label_index {k} but only {len(boxes)} rows")
        box, rest = boxes[k], np.delete(boxes, k, axis=0)
        shares = visibility.footprint_shares(box, rest)
        rows.append({**shares, "curvature": inpath.lane_curvature(box, float(offset)),
                     "rear_m": float(inpath.rear_face(box, box[6])[0])})
        slow.append(box)
        others.append(rest)
    ref = pd.DataFrame(rows, index=frames.index, columns=["unoccluded", "in_range", "visible", "curvature", "rear_m"])
    frames = pd.concat([frames, ref], axis=1).assign(perceivable=lambda f: f["visible"] >= visible_min)
    return Reference(data_dir, frames, np.asarray(slow, dtype=np.float64).reshape(-1, 7), others)


def check_predictions(data_dir, predictions_dir) -> None:
    """KittiError naming the file: a result file (``*.txt``) of a frame the set does not hold."""
    predictions_dir = Path(predictions_dir)
    if not predictions_dir.is_dir():
        raise KittiError(predictions_dir, "prediction folder not found")
    known = set(load_meta(data_dir)["frame_id"])
    for path in sorted(predictions_dir.glob("*.txt")):
        if path.stem not in known:
            raise KittiError(path, f"predictions for frame {path.stem!r}, which the data set {data_dir} does not hold")


def detector_frames(ref: Reference, predictions_dir, threshold: float) -> pd.DataFrame:
    """Per judged frame (``ref.frames``' order): ``hit`` (an in-path hit on the slow vehicle), ``iou_hit`` (a kept
    box at BEV IoU >= 0.5 with it), ``n_phantom`` (phantom in-path boxes) and ``predicted`` (a result file
    exists: always, as a judged frame without one is refused, naming it, as ``evaluate`` does). Boxes scoring below
    ``threshold`` and DontCare rows are dropped."""
    predictions_dir = Path(predictions_dir)
    missing = [fid for fid in ref.frames["frame_id"] if not (predictions_dir / f"{fid}.txt").is_file()]
    if missing:  # no file is not "nothing found": a cut-off predict would pass for a blind detector
        raise KittiError(predictions_dir / f"{missing[0]}.txt",
                         f"file not found ({len(missing)} of the {len(ref.frames)} judged frames lack one; every "
                         "frame needs one, empty if nothing was found)")
    rows = []
    for i, fid in enumerate(ref.frames["frame_id"]):
        path = predictions_dir / f"{fid}.txt"
        boxes, scores, names = lidar_boxes(ref.data_dir, path, fid)
        boxes = boxes[(scores >= threshold) & (names != "DontCare")]
        slow = ref.slow[i]
        objects = np.concatenate([slow[None], ref.others[i]])
        rows.append({"hit": bool(inpath.inpath_hits(boxes, slow).any()),
                     "iou_hit": bool(len(boxes) and (iou_bev(boxes, slow[None])[:, 0] >= IOU_BEV_MIN).any()),
                     "n_phantom": int(inpath.phantoms(boxes, objects, ref.frames["curvature"].iat[i]).sum()),
                     "predicted": True})  # every judged frame has its file (checked above)
    return pd.DataFrame(rows, index=ref.frames.index, columns=["hit", "iou_hit", "n_phantom", "predicted"])
