"""What a two-stage model's second stage changes, box value by box value.

For every proposal (``rois``) whose BEV centre lies within 1 m of a labelled car, the absolute error
of each box value (x, y, z, l, w, h, yaw; yaw modulo pi) at the proposal and at its refined box
(``rcnn_boxes``, the same row), on the val frames of a run's training data set through
onnxruntime; mean and median per value. A second stage that refines lowers the errors; where it
leaves one unchanged, that value's 3D IoU loss stays the proposal's (a 0.12 m height error costs a
1.5 m tall car about 8 % of its 3D IoU). Then the share of those proposals whose rotated 3D IoU
with the car reaches 0.7: as proposed, with the car's own z and height put in (what the two
vertical values cost), and refined.

    python -m benchmarks.refine_check RUN_DIR [--models parta2,pv_rcnn,point_rcnn] [--split val]
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from harness.boxes import iou_3d
from harness.dataset import KittiDataset
from harness.infer import OnnxDetector

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
    shares = {}
    for name in args.models.split(","):
        det = OnnxDetector(args.run / "models" / f"{name}.onnx", threads=args.threads)
        if "rcnn_boxes" not in det.output_names:
            print(f"| {name} | not a two-stage graph (no rcnn_boxes) |")
            continue
        roi_err, rcnn_err, ious = [], [], []
        for i in range(len(ds)):
            sample = ds[i]
            out = det(sample.points)
            a, b, c = matched_errors(out["rois"], out["rcnn_boxes"], sample.boxes_of("Car"))
            roi_err.append(a)
            rcnn_err.append(b)
            ious.append(c)
        for stage, errs in (("RoI", roi_err), ("RCNN", rcnn_err)):
            e = np.concatenate(errs)
            cells = " | ".join(f"{m:.3f} ({md:.3f})" for m, md in zip(e.mean(0), np.median(e, 0))) if len(e) else ""
            print(f"| {name} | {len(e)} | {stage} | {cells} |", flush=True)
        shares[name] = (np.concatenate(ious) >= 0.7).mean(0) if sum(len(c) for c in ious) else None
    print()
    print("| model | 3D IoU >= 0.7: proposals | proposals with the car's z and height | refined |")
    print("|---|---|---|---|")
    for name, share in shares.items():
        if share is not None:
            print(f"| {name} | {share[0]:.0%} | {share[1]:.0%} | {share[2]:.0%} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
