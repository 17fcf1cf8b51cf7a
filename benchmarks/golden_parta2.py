"""Golden data of OpenPCDet's Part-A2 (``tools/cfgs/kitti_models/PartA2.yaml``, the anchor-based
Part-A2-Anchor), made by OpenPCDet's own modules.

    PYTHONPATH=SPCONV:EASYDICT python -m benchmarks.golden_parta2 --openpcdet PATH/OpenPCDet [--out tests/golden]

needs what ``benchmarks/golden_published.py`` needs (spconv 2.3.8 on CPU with cumm 0.7.x, easydict,
shapely, a source checkout of OpenPCDet that is never built). The detector's modules are OpenPCDet's,
built from the config as ``Detector3DTemplate`` builds them (``MeanVFE``, ``UNetV2``,
``HeightCompression``, ``BaseBEVBackbone``, ``AnchorHeadSingle``, ``PointIntraPartOffsetHead``,
``PartA2FCHead``) and run in that order; the post-processing is ``Detector3DTemplate.post_processing``'s
class-agnostic branch (``class_agnostic_nms`` on the RCNN scores, labels from the RoIs). Two of its
ops are CUDA-only and get CPU stand-ins with the kernels' contracts:

- ``nms_gpu`` (proposal layer and final NMS): ``benchmarks.golden_published.cpu_nms``.
- ``roiaware_pool3d_cuda.forward`` (``pcdet/ops/roiaware_pool3d/src/roiaware_pool3d_kernel.cu``):
  :func:`roiaware_pool3d_forward`, the kernel's arithmetic in float32 numpy.

The checkpoint tensors are filled by the seeded rule golden-weights-2 of ``benchmarks.golden_weights`` (the
RCNN's shared fully connected layer of 56.6 M weights drawn uniform in float32, cheap to rebuild); one frame
(``benchmarks.golden_published.frame``) runs twice on one thread (spconv's CPU scatter-add races on
more) and nothing is written unless both runs agree bit for bit. ``tests/golden/openpcdet_parta2.npz``
holds the rule's seed, the tensor names and shapes (no weights), the frame, sampled intermediates
(the bird's-eye map entering the 2D backbone, the RPN class logits, the voxels' segmentation and
part scores with the voxels' centres), the 100 proposals (boxes, scores, labels), the RCNN logits and
boxes of every proposal and the final boxes of every class with labels and scores.
"""
from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import torch
from torch import nn

from benchmarks.golden_published import frame as published_frame
from benchmarks.golden_published import (TWO_STAGE, import_openpcdet, iou, openpcdet_config, polygon, reference_main,
                                         repeatable, sampled_entries, seeded, two_stage_counts, voxelize)

SEED, CLS_BIAS, RULE = 500, -2.0, "golden-weights-2"
GROUND = 8000
MARGIN = np.float32(1e-5)  # check_pt_in_box3d's MARGIN


def frame(seed: int) -> np.ndarray:
    """(N, 4) float32 points: ``benchmarks.golden_published.frame``'s cars and outliers on a ground of
    GROUND points (1.4 a square metre, beside the 1.1 of golden_published: fewer proposals hold no voxel)."""
    rng = np.random.Generator(np.random.PCG64(seed))
    ground = np.c_[rng.uniform(0, 70.4, GROUND), rng.uniform(-40, 40, GROUND), rng.normal(-1.75, 0.02, GROUND),
                   rng.uniform(0, 1, GROUND)].astype(np.float32)
    return np.concatenate([ground, published_frame(seed)[6000:]])


def roiaware_pool3d_forward(rois, pts, pts_feature, argmax, pts_idx_of_voxels, pooled_features, pool_method):
    """CPU stand-in of ``roiaware_pool3d_cuda.forward`` (same arguments, fills ``pooled_features``).

    As the kernels: a point is in a RoI when |z - cz| <= dz / 2 and its canonical |x|, |y| are below
    dx / 2 + 1e-5, dy / 2 + 1e-5 (compared in double, as the kernel's ``dx / 2.0``); its cell is
    int((local + d / 2) / (d / out)) per axis (truncation, clamped to [0, out - 1]); a cell takes the
    first max_pts_each_voxel - 1 points in point order; max pool (0) keeps the largest value over them
    (an empty cell stays 0), avg pool (1) their mean."""
    boxes, xyz = rois.numpy().astype(np.float32), pts.numpy().astype(np.float32)
    feats = pts_feature.numpy()
    _, out_x, out_y, out_z, _ = pooled_features.shape
    cap = pts_idx_of_voxels.shape[-1] - 1
    out = np.zeros(pooled_features.shape, np.float32)
    for b, box in enumerate(boxes):
        cx, cy, cz, dx, dy, dz, rz = (np.float32(v) for v in box)
        cosa, sina = np.cos(-rz, dtype=np.float32), np.sin(-rz, dtype=np.float32)
        sx, sy = xyz[:, 0] - cx, xyz[:, 1] - cy
        local_x = sx * cosa + sy * (-sina)
        local_y = sx * sina + sy * cosa
        inside = ((np.abs(xyz[:, 2] - cz).astype(np.float64) <= np.float64(dz) / 2.0)
                  & (np.abs(local_x).astype(np.float64) < np.float64(dx) / 2.0 + np.float64(MARGIN))
                  & (np.abs(local_y).astype(np.float64) < np.float64(dy) / 2.0 + np.float64(MARGIN)))
        k = np.flatnonzero(inside)  # point order
        local_z = xyz[k, 2] - cz
        idx = [np.clip(np.trunc((loc + d / np.float32(2)) / (d / np.float32(n))).astype(np.int64), 0, n - 1)
               for loc, d, n in ((local_x[k], dx, out_x), (local_y[k], dy, out_y), (local_z, dz, out_z))]
        cell = (idx[0] * out_y + idx[1]) * out_z + idx[2]
        order = np.argsort(cell, kind="stable")  # point order within a cell
        cell, k = cell[order], k[order]
        first = np.r_[0, np.flatnonzero(np.diff(cell)) + 1]
        rank = np.arange(len(cell)) - np.repeat(first, np.diff(np.r_[first, len(cell)]))
        cell, k = cell[rank < cap], k[rank < cap]
        flat = out[b].reshape(-1, out.shape[-1])
        if pool_method == 0:
            acc = np.full_like(flat, -np.inf)
            np.maximum.at(acc, cell, feats[k])
            flat[:] = np.where(np.isinf(acc), 0, acc)
        else:
            acc = np.zeros_like(flat)
            for c, p in zip(cell, k):  # the kernel's float32 sum in point order
                acc[c] += feats[p]
            count = np.bincount(cell, minlength=len(flat)).astype(np.float32)[:, None]
            flat[:] = np.where(count > 0, acc / np.maximum(count, 1), 0)
    pooled_features.copy_(torch.from_numpy(out))


def import_parta2(root: Path) -> None:
    """OpenPCDet's modules as ``golden_published.import_openpcdet``, plus the RoI-head packages and
    the RoI-aware pooling stand-in."""
    import_openpcdet(root)
    for name in ("pcdet.models.roi_heads", "pcdet.models.roi_heads.target_assigner"):
        module = types.ModuleType(name)
        module.__path__ = [str(root.joinpath(*name.split(".")))]
        sys.modules[name] = module
    sys.modules["pcdet.ops.roiaware_pool3d.roiaware_pool3d_cuda"].forward = roiaware_pool3d_forward


def build(root: Path):
    """Part-A2's modules under OpenPCDet's module names, its data-processing and post-processing configs."""
    from pcdet.models.backbones_2d.base_bev_backbone import BaseBEVBackbone
    from pcdet.models.backbones_2d.map_to_bev.height_compression import HeightCompression
    from pcdet.models.backbones_3d.spconv_unet import UNetV2
    from pcdet.models.backbones_3d.vfe.mean_vfe import MeanVFE
    from pcdet.models.dense_heads.anchor_head_single import AnchorHeadSingle
    from pcdet.models.dense_heads.point_intra_part_head import PointIntraPartOffsetHead
    from pcdet.models.roi_heads.partA2_head import PartA2FCHead

    cfg, proc = openpcdet_config(root / "tools" / "cfgs" / "kitti_models" / "PartA2.yaml")
    r, vs, m = np.array(proc.POINT_CLOUD_RANGE), np.array(proc.VOXEL_SIZE), cfg.MODEL
    grid = np.round((r[3:] - r[:3]) / vs).astype(np.int64)
    n = len(cfg.CLASS_NAMES)
    net = nn.Module()
    net.register_buffer("global_step", torch.LongTensor(1).zero_())
    net.vfe = MeanVFE(m.VFE, 4)
    net.backbone_3d = UNetV2(m.BACKBONE_3D, 4, grid, vs, r)
    net.map_to_bev_module = HeightCompression(m.MAP_TO_BEV)
    net.backbone_2d = BaseBEVBackbone(m.BACKBONE_2D, m.MAP_TO_BEV.NUM_BEV_FEATURES)
    net.dense_head = AnchorHeadSingle(m.DENSE_HEAD, net.backbone_2d.num_bev_features, n, cfg.CLASS_NAMES, grid, r,
                                      predict_boxes_when_training=True)
    c = net.backbone_3d.num_point_features
    net.point_head = PointIntraPartOffsetHead(1 if m.POINT_HEAD.CLASS_AGNOSTIC else n, c, m.POINT_HEAD)
    net.roi_head = PartA2FCHead(c, m.ROI_HEAD, num_class=1 if m.ROI_HEAD.CLASS_AGNOSTIC else n)
    return net.eval(), proc, m.POST_PROCESSING, cfg.CLASS_NAMES


def order_free(scores: np.ndarray, boxes: np.ndarray, nms) -> str | None:
    """None when ``class_agnostic_nms`` (``nms``: its config) keeps the same boxes, in the same order up to
    equal scores, whatever the order among equal scores; else why not. Equal scores are real: every RoI
    holding no voxel gets the same RCNN output. The order among them is the sort's (the reference's
    torch.topk / sort, ours the lower index), so golden data must not depend on it: no tie at the
    NMS_PRE cut, no two boxes of one score overlapping by more than NMS_THRESH, and the last box kept at
    the NMS_POST cap sharing its score with no other candidate."""
    order = np.argsort(-scores, kind="stable")
    pre = nms.NMS_PRE_MAXSIZE
    if len(order) > pre and scores[order[pre - 1]] == scores[order[pre]]:
        return "a tie at the NMS_PRE_MAXSIZE cut"
    top = order[:nms.NMS_PRE_MAXSIZE]
    values, counts = np.unique(scores[top], return_counts=True)
    for v in values[counts > 1]:
        polys = [polygon(b) for b in boxes[top[scores[top] == v]].astype(np.float64)]
        if any(iou(a, b) > nms.NMS_THRESH for i, a in enumerate(polys) for b in polys[i + 1:]):
            return f"{len(polys)} boxes of score {v} of which two overlap by more than {nms.NMS_THRESH}"
    return None


def capped_tie(scores: np.ndarray, kept: np.ndarray, cap: int) -> str | None:
    """Why the first ``cap`` of the boxes kept (indices, best first) depend on the order among equal scores, or None."""
    if len(kept) >= cap and np.sum(scores == scores[kept[cap - 1]]) > 1:
        return "a tie at the NMS_POST_MAXSIZE cut"
    return None


MODULES = ("vfe", "backbone_3d", "map_to_bev_module", "backbone_2d", "dense_head", "point_head", "roi_head")


def run(net, proc, post, points: np.ndarray) -> dict:
    """The reference forward on one frame: intermediates, proposals, RCNN outputs and final boxes."""
    from pcdet.models.model_utils import model_nms_utils

    batch = voxelize(points, proc)
    seen = {}
    with torch.no_grad():
        for name in MODULES:
            if name == "roi_head":  # the RPN's outputs, before the RoI head replaces them
                seen["cls"] = batch["batch_cls_preds"][0].clone()
                seen["rpn_boxes"] = batch["batch_box_preds"][0].clone()
            batch = getattr(net, name)(batch)
        rcnn_cls, boxes = batch["batch_cls_preds"][0], batch["batch_box_preds"][0]  # (K, 1) logits, (K, 7)
        scores = torch.sigmoid(rcnn_cls).max(dim=-1).values  # post_processing: has_class_labels -> roi_labels
        selected, selected_scores = model_nms_utils.class_agnostic_nms(scores, boxes, post.NMS_CONFIG,
                                                                       post.SCORE_THRESH)
    rpn_scores = seen["cls"].max(dim=1).values.numpy()  # the proposal layer's (logits)
    proposal_nms = net.roi_head.model_cfg.NMS_CONFIG.TEST
    passed = np.flatnonzero(scores.numpy() >= post.SCORE_THRESH)
    why = (order_free(rpn_scores, seen["rpn_boxes"].numpy(), proposal_nms)
           or order_free(scores.numpy()[passed], boxes.numpy()[passed], post.NMS_CONFIG)
           or capped_tie(scores.numpy(), selected.numpy(), post.NMS_CONFIG.NMS_POST_MAXSIZE)
           or capped_tie(rpn_scores, np.flatnonzero(rpn_scores == batch["roi_scores"][0, -1].item()),
                         1))  # the proposals' last score is no other anchor's
    if why is not None:
        raise TieError(why)
    return {"num_voxels": batch["voxel_coords"].shape[0], "bev": batch["spatial_features"][0], "cls": seen["cls"],
            "seg": batch["point_cls_scores"], "part": batch["point_part_offset"],
            "xyz": batch["point_coords"][:, 1:4].numpy(), "rois": batch["rois"][0].numpy(),
            "roi_scores": batch["roi_scores"][0].numpy(), "roi_labels": batch["roi_labels"][0].numpy() - 1,
            "rcnn_cls": rcnn_cls[:, 0].numpy(), "rcnn_boxes": boxes.numpy(), "boxes": boxes[selected].numpy(),
            "scores": selected_scores.numpy(), "labels": batch["roi_labels"][0][selected].numpy() - 1}


class TieError(RuntimeError):
    """The reference's result depends on how its sort orders equal scores (``order_free``)."""


def golden(root: Path, out: Path, seed: int = SEED) -> Path:
    net, proc, post, classes = build(root)
    weights = seeded(net, seed, CLS_BIAS, rule=RULE)
    points = frame(seed)
    res = repeatable(run, net, proc, post, points)
    sampled = sampled_entries(res, ("bev", "cls", "seg", "part"), seed + 1)
    for key in ("seg", "part"):  # the voxels' order is the voxelizer's: they are found by their centres
        sampled[f"{key}_xyz"] = res["xyz"][sampled[f"{key}_index"][:, 0]]
    path = out / "openpcdet_parta2.npz"
    np.savez_compressed(path, **weights, points=points, num_voxels=res["num_voxels"], **sampled,
                        **{k: res[k] for k in TWO_STAGE}, classes=np.array(classes))
    print(f"{path}: {res['num_voxels']} voxels, {two_stage_counts(res)}")
    return path


def main(argv=None) -> int:
    return reference_main(argv, __doc__.splitlines()[0], import_parta2, golden, SEED)


if __name__ == "__main__":
    sys.exit(main())
