"""The proposal NMS of a trained PointRCNN on SOTIF frames: what its parts cost, eager and in the graph.

Per frame, the ``pre_nms`` points PointRCNN decodes into boxes (its own ``stage_one`` and
``decode_bins``), then ``models.nms.nms_in_order`` at its proposal IoU: the pairs the
axis-aligned pre-filter passes, the pairs whose rotated IoU suppresses, the fixed-point rounds
and the boxes kept; the eager time of each part (torch, one thread) and the time of the whole NMS
exported alone to ONNX and run by onnxruntime (one thread), median over the frames.

    python benchmarks/bench_nms.py RUN_DIR [--frames 5] [--first 100]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from harness.dataset import KittiDataset
from models.iou import iou_bev_pairs
from models.nms import fixed_point_round, nms_in_order, suppression_candidates
from models.zoo import load_checkpoint


class ProposalNMS(torch.nn.Module):
    def __init__(self, iou_thresh: float):
        super().__init__()
        self.iou_thresh = iou_thresh

    def forward(self, boxes):
        return nms_in_order(boxes, self.iou_thresh)


def proposal_boxes(model, points: np.ndarray) -> torch.Tensor:
    """(pre_nms, 7) decoded boxes of the best-scored points, best first (the proposal NMS's input)."""
    with torch.no_grad():
        pts, _ = model.points_of_interest(torch.from_numpy(points))
        _, seg, box = model.stage_one(pts)
        return model.decode_top(pts, seg, box)[2]


def rounds(j: torch.Tensor, i: torch.Tensor, k: int) -> int:
    """Fixed-point rounds until the keep mask stops changing (the graph's Loop trip count)."""
    keep, n = torch.ones(k, dtype=torch.bool), 0
    while True:
        n += 1
        new = fixed_point_round(keep, j, i)
        if bool((new == keep).all()):
            return n
        keep = new


def timed(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path)
    p.add_argument("--frames", type=int, default=5)
    p.add_argument("--first", type=int, default=100, help="first SOTIF test frame (100-119: the overtaking)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    model, _ = load_checkpoint(args.run / "models" / "point_rcnn" / "checkpoint.pt")
    thresh = model.cfg.proposal_nms_iou
    ds = KittiDataset(args.run / "data" / "sotif", "test")
    frames = [proposal_boxes(model, ds[n].points) for n in range(args.first, min(len(ds), args.first + args.frames))]

    path = Path(tempfile.mkdtemp()) / "nms.onnx"
    k = torch.export.Dim("k", min=2, max=16384)
    torch.onnx.export(ProposalNMS(thresh), (frames[0],), str(path), dynamo=True, opset_version=18,
                      input_names=["boxes"], dynamic_shapes=({0: k},), verbose=False)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads, opts.inter_op_num_threads, opts.log_severity_level = 1, 1, 3
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])

    print(f"PointRCNN proposal NMS, BEV IoU {thresh}, {len(frames)} SOTIF frames from {args.first}, one thread; ms")
    print("| frame | boxes | pre-filter pairs | suppressing pairs | rounds | kept | eager pre-filter | eager IoU "
          "| eager fixed point | eager NMS | onnxruntime NMS |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    ort_ms, eager_ms = [], []
    for n, boxes in enumerate(frames, start=args.first):
        kk = boxes.shape[0]
        cand = suppression_candidates(boxes, thresh)
        j, i = torch.nonzero(cand, as_tuple=True)
        over = iou_bev_pairs(boxes[j], boxes[i]) > thresh
        js, is_ = j[over], i[over]
        kept = nms_in_order(boxes, thresh)
        got = sess.run(None, {"boxes": boxes.numpy()})[0]
        if not np.array_equal(got, kept.numpy()):
            raise SystemExit(f"frame {n}: onnxruntime keeps other boxes than torch")
        t_cand = timed(lambda: torch.nonzero(suppression_candidates(boxes, thresh), as_tuple=True))
        t_iou = timed(lambda: iou_bev_pairs(boxes[j], boxes[i]) > thresh)
        n_rounds = rounds(js, is_, kk)
        t_fix = timed(lambda: rounds(js, is_, kk))
        t_all = timed(lambda: nms_in_order(boxes, thresh))
        t_ort = timed(lambda: sess.run(None, {"boxes": boxes.numpy()}))
        eager_ms.append(t_all)
        ort_ms.append(t_ort)
        print(f"| {n} | {kk} | {len(j)} | {len(js)} | {n_rounds} | {len(kept)} | {t_cand:.1f} | "
              f"{t_iou:.1f} | {t_fix:.1f} | {t_all:.1f} | {t_ort:.1f} |")
    print(f"median: eager {np.median(eager_ms):.1f} ms, onnxruntime {np.median(ort_ms):.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
