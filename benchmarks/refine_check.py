"""What a two-stage model's second stage changes, box value by box value.

For every proposal (``rois``) whose BEV centre lies within 1 m of a labelled car, the absolute error
of each box value (x, y, z, l, w, h, yaw; yaw modulo pi) at the proposal and at its refined box
(``rcnn_boxes``, the same row), on the val frames of a run's training data set through
onnxruntime; mean and median per value. A second stage that refines lowers the errors; where it
leaves one unchanged, that value's 3D IoU loss stays the proposal's (a 0.12 m height error costs a
1.5 m tall car about 8 % of its 3D IoU). Then the share of those proposals whose rotated 3D IoU
with the car reaches 0.7: as proposed, with the car's own z and height put in (what the two
vertical values cost), and refined.

Last, what the scores cost: val AP40 (3D, IoU 0.7, KITTI moderate) of the model's output, and of
its refined boxes and of its proposals each ranked by their own 3D IoU with the nearest car (the
score an ideal confidence would give; then the same final NMS, BEV IoU 0.1). The gap between the
output and the refined boxes so ranked is AP lost to the confidence alone.

    python -m benchmarks.refine_check RUN_DIR [--models parta2,pv_rcnn,point_rcnn] [--split val]
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

from harness.core.boxes import iou_3d
from harness.core.kitti import IMAGE_SIZE
from harness.dataset import KittiDataset
from harness.eval_kitti import build_eval_set, kitti_ap
from harness.infer import OnnxDetector, boxes_to_results
from models.nms import select_ranked

NAMES = ("x", "y", "z", "l", "w", "h", "yaw")


def box_errors(boxes: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """|boxes - gt| per value (K, 7); yaw difference wrapped to [-pi/2, pi/2) (a box either way)."""
    err = boxes - gt
    err[:, 6] = (err[:, 6] + math.pi / 2) % math.pi - math.pi / 2
    return np.abs(err)


def matched_errors(rois: np.ndarray, refined: np.ndarray, cars: np.ndarray, radius: float = 1.0):
    """Errors (P, 7) of the proposals within ``radius`` m (BEV centre) of a car, and of their refined
    boxes; and their 3D IoUs with that car (P, 3): proposal, proposal with the car's z and height,
    refined box."""
    at_roi, at_rcnn, ious = [], [], []
    for car in cars:
        near = np.hypot(rois[:, 0] - car[0], rois[:, 1] - car[1]) < radius
        if near.any():
            gt = np.asarray(car, np.float64)[None]
            at_roi.append(box_errors(rois[near], gt))
            at_rcnn.append(box_errors(refined[near], gt))
            level = np.array(rois[near], np.float64)
            level[:, [2, 5]] = gt[:, [2, 5]]
            ious.append(np.stack([iou_3d(rois[near], gt)[:, 0], iou_3d(level, gt)[:, 0],
                                  iou_3d(refined[near], gt)[:, 0]], 1))
    if not at_roi:
        return np.zeros((0, 7)), np.zeros((0, 7)), np.zeros((0, 3))
    return np.concatenate(at_roi), np.concatenate(at_rcnn), np.concatenate(ious)


def ranked_by_iou(boxes: np.ndarray, cars: np.ndarray, nms_iou: float = 0.1,
                  max_out: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """boxes (K, 7) scored by their best rotated 3D IoU with cars (G, 7), then the final NMS:
    -> (M, 7), (M,). Boxes overlapping no car get score 0 and are dropped (ranked below every
    true positive, they would not change the AP)."""
    if not len(boxes) or not len(cars):
        return np.zeros((0, 7), np.float32), np.zeros(0, np.float32)
    score = iou_3d(boxes, cars).max(1).astype(np.float32)
    kept, scores = select_ranked(torch.from_numpy(np.asarray(boxes, np.float32)), torch.from_numpy(score),
                                 0.0, len(boxes), nms_iou, max_out)
    return kept.numpy(), scores.numpy()


def moderate_ap(gt: list, dt: list) -> float:
    """AP40 3D at IoU 0.7, KITTI moderate, of result labels against ground-truth labels."""
    return kitti_ap(build_eval_set(gt, dt))["3d"]["0.7"]["R40"]["moderate"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path)
    p.add_argument("--models", default="parta2,pv_rcnn,point_rcnn")
    p.add_argument("--split", default="val")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    ds = KittiDataset(args.run / "data" / "train", args.split)
    print(f"{len(ds)} {args.split} frames of {args.run / 'data' / 'train'}; proposals within 1 m of a car; "
          "mean (median) |error| in m, yaw in rad")
    print("| model | proposals | stage | " + " | ".join(NAMES) + " |")
    print("|---|---|---|" + "---|" * len(NAMES))
    shares, aps = {}, {}
    for name in args.models.split(","):
        det = OnnxDetector(args.run / "models" / f"{name}.onnx", threads=args.threads)
        if "rcnn_boxes" not in det.output_names:
            print(f"| {name} | not a two-stage graph (no rcnn_boxes) |")
            continue
        roi_err, rcnn_err, ious = [], [], []
        gt, dt = [], {"output": [], "refined": [], "proposals": []}
        for i in range(len(ds)):
            sample = ds[i]
            out = det(sample.points)
            cars = sample.boxes_of("Car")
            a, b, c = matched_errors(out["rois"], out["rcnn_boxes"], cars)
            calib, hw = ds.calib(i), IMAGE_SIZE[::-1]
            gt.append(ds.labels(i))
            dt["output"].append(boxes_to_results(out["boxes"], out["scores"], calib, hw))
            dt["refined"].append(boxes_to_results(*ranked_by_iou(out["rcnn_boxes"], cars), calib, hw))
            dt["proposals"].append(boxes_to_results(*ranked_by_iou(out["rois"], cars), calib, hw))
            roi_err.append(a)
            rcnn_err.append(b)
            ious.append(c)
        for stage, errs in (("RoI", roi_err), ("RCNN", rcnn_err)):
            e = np.concatenate(errs)
            cells = " | ".join(f"{m:.3f} ({md:.3f})" for m, md in zip(e.mean(0), np.median(e, 0))) if len(e) else ""
            print(f"| {name} | {len(e)} | {stage} | {cells} |", flush=True)
        shares[name] = (np.concatenate(ious) >= 0.7).mean(0) if sum(len(c) for c in ious) else None
        aps[name] = {k: moderate_ap(gt, v) for k, v in dt.items()}
    print()
    print("| model | 3D IoU >= 0.7: proposals | proposals with the car's z and height | refined |")
    print("|---|---|---|---|")
    for name, share in shares.items():
        if share is not None:
            print(f"| {name} | {share[0]:.0%} | {share[1]:.0%} | {share[2]:.0%} |")
    print()
    print("| model | AP40 3D moderate: output | refined boxes ranked by their 3D IoU | proposals ranked by their 3D IoU |")
    print("|---|---|---|---|")
    for name, ap in aps.items():
        print(f"| {name} | {ap['output']:.1f} | {ap['refined']:.1f} | {ap['proposals']:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
