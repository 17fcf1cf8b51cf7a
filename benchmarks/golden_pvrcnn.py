"""Golden data of OpenPCDet's PV-RCNN (``tools/cfgs/kitti_models/pv_rcnn.yaml``), made by OpenPCDet's own modules.

    PYTHONPATH=SPCONV:EASYDICT python -m benchmarks.golden_pvrcnn --openpcdet PATH/OpenPCDet [--out tests/golden]

needs what ``benchmarks/golden_parta2.py`` needs. The detector's modules are OpenPCDet's, built from the
config as ``Detector3DTemplate`` builds them and registered in its order (``MeanVFE``, ``VoxelBackBone8x``,
``HeightCompression``, ``VoxelSetAbstraction``, ``BaseBEVBackbone``, ``AnchorHeadSingle``,
``PointHeadSimple``, ``PVRCNNHead``), run in that order; the post-processing is
``Detector3DTemplate.post_processing``'s class-agnostic branch, as for Part-A2. Its CUDA-only ops get CPU
stand-ins with the kernels' contracts (``pcdet/ops/pointnet2/pointnet2_stack/src``):

- ``farthest_point_sample`` (``sampling_gpu.cu``, ``farthest_point_sampling_kernel``): :func:`fps`;
- ``ball_query`` (``ball_query_gpu.cu``, ``ball_query_kernel_stack``): :func:`ball_query`;
- ``grouping_operation`` (``group_points_gpu.cu``): :func:`grouping_operation`;
- ``nms_gpu`` (proposal layer and final NMS): ``benchmarks.golden_published.cpu_nms``.

The network reads the points as OpenPCDet's data processing leaves them at test time: x and y within the
range, ends included (``mask_points_by_range``), in file order. The frame is golden_parta2's. Besides the
ties golden_parta2 refuses (``order_free``, ``capped_tie``), a frame is refused when the result depends on
float rounding below what the comparison resolves: a keypoint within ``BALL_MARGIN`` of the radius of a ball
that it may enter, around a grid point of a RoI whose box is kept (our proposals differ from the
reference's by a few float32 ulps, and a keypoint that leaves a ball changes that RoI's box by far more
than 1e-3). Ties of the FPS (two points at
the same largest distance) are counted and the sampled indices recorded, so the comparison is exact.
The checkpoint tensors are filled by golden_parta2's rule (golden-weights-2).
``tests/golden/openpcdet_pv_rcnn.npz`` holds the rule's seed, the tensor names and shapes (no weights), the
frame, the keypoints' indices into the in-range points, sampled intermediates (the bird's-eye map, the RPN
class logits, the keypoint features before and after the fusion, every keypoint's weight), the 100
proposals, the RCNN logits and boxes of every proposal and the final boxes of every class with labels and
scores.
"""
from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import torch
from torch import nn

from benchmarks.golden_parta2 import RULE, TieError, capped_tie, frame, order_free
from benchmarks.golden_published import (TWO_STAGE, import_openpcdet, openpcdet_config, reference_main, repeatable,
                                         sampled_entries, seeded, two_stage_counts, voxelize)

SEED, CLS_BIAS = 621, -2.0
BALL_MARGIN = 1e-5  # metres: a keypoint this close to a RoI grid ball's surface makes the frame fragile
STATS = {"fps_ties": 0}


def fps(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """CPU stand-in of ``farthest_point_sample`` (B, N, 3) -> (B, npoint) int32, the kernel's float32
    arithmetic: distances to the last pick ``(x2 - x1)^2 + (y2 - y1)^2 + (z2 - z1)^2`` summed left to right
    (no fused multiply-add), ``min`` with the running distance (from 1e10), the largest taken. On equal
    largest distances the kernel's thread ``k % block`` keeps its lowest point k and the block's tree
    reduction (``__update``: the lower slot wins a tie) chooses among the threads: simulated, and counted
    in ``STATS``."""
    pts = xyz.numpy().astype(np.float32)
    b, n, _ = pts.shape
    block = max(min(1 << int(np.log2(n)), 1024), 1) if n else 1  # opt_n_threads
    out = np.zeros((b, npoint), np.int32)
    for r in range(b):
        x, y, z = pts[r, :, 0], pts[r, :, 1], pts[r, :, 2]
        temp = np.full(n, 1e10, np.float32)
        old = 0
        for j in range(1, npoint):
            dx, dy, dz = x - x[old], y - y[old], z - z[old]
            d = dx * dx + dy * dy
            d = d + dz * dz
            temp = np.minimum(d, temp)
            best = temp.max()
            tied = np.flatnonzero(temp == best)
            old = int(tied[0]) if len(tied) == 1 else _tree_winner(tied, block)
            STATS["fps_ties"] += len(tied) > 1
            out[r, j] = old
    return torch.from_numpy(out)


def _tree_winner(tied: np.ndarray, block: int) -> int:
    """The point the kernel picks among equally far points ``tied`` (ascending)."""
    slot = {}
    for k in tied:  # each thread's first (lowest) point of the largest distance
        slot.setdefault(int(k) % block, int(k))
    present = np.zeros(block, bool)
    index = np.zeros(block, np.int64)
    for t, k in slot.items():
        present[t], index[t] = True, k
    s = block // 2
    while s >= 1:
        for t in range(s):  # __update(t, t + s): the upper slot replaces only a strictly larger value
            if present[t + s] and not present[t]:
                present[t], index[t] = True, index[t + s]
        s //= 2
    return int(index[0])


def ball_query(radius: float, nsample: int, xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt):
    """CPU stand-in of the stacked ``ball_query`` -> (idx (M, nsample) int32, empty_ball_mask (M,)), one
    batch: the first ``nsample`` points in index order with ``d2 < radius2`` (``radius2 = radius * radius``
    in float32, d2 summed x, y, z in float32), the rest of the row the first one; an empty ball's row is 0
    and its mask True (the Python wrapper's ``idx[empty_ball_mask] = 0``)."""
    assert len(xyz_batch_cnt) == 1 and len(new_xyz_batch_cnt) == 1
    pts, ctr = xyz.numpy().astype(np.float32), new_xyz.numpy().astype(np.float32)
    r2 = np.float32(radius) * np.float32(radius)
    idx = np.zeros((len(ctr), nsample), np.int32)
    empty = np.zeros(len(ctr), bool)
    for lo in range(0, len(ctr), 512):
        c = ctr[lo:lo + 512]
        dx, dy, dz = (c[:, None, i] - pts[None, :, i] for i in range(3))  # (m, N) each
        d2 = dx * dx + dy * dy
        d2 = d2 + dz * dz
        inside = d2 < r2
        rank = np.cumsum(inside, axis=1)  # (m, N) neighbours up to each point
        for row, (mask, count) in enumerate(zip(inside, rank[:, -1] if len(pts) else np.zeros(len(c), int))):
            first = np.flatnonzero(mask & (rank[row] <= nsample))
            if count == 0:
                empty[lo + row] = True
                continue
            idx[lo + row] = first[0]
            idx[lo + row, :len(first)] = first
    return torch.from_numpy(idx), torch.from_numpy(empty)


def grouping_operation(features, features_batch_cnt, idx, idx_batch_cnt):
    """CPU stand-in of the stacked ``grouping_operation``: (M, C, nsample) = features[idx] (one batch)."""
    assert len(features_batch_cnt) == 1 and len(idx_batch_cnt) == 1
    return features[idx.long()].permute(0, 2, 1).contiguous()


def import_pvrcnn(root: Path) -> None:
    """OpenPCDet's modules as ``golden_published.import_openpcdet``, plus the RoI-head, PFE and pointnet2
    packages with the stand-ins above."""
    import_openpcdet(root)
    for name in ("pcdet.models.roi_heads", "pcdet.models.roi_heads.target_assigner", "pcdet.models.backbones_3d.pfe",
                 "pcdet.ops.pointnet2", "pcdet.ops.pointnet2.pointnet2_stack"):
        module = types.ModuleType(name)
        module.__path__ = [str(root.joinpath(*name.split(".")))]
        sys.modules[name] = module
    sys.modules["pcdet.ops.pointnet2.pointnet2_stack.pointnet2_stack_cuda"] = types.ModuleType("pointnet2_stack_cuda")
    from pcdet.ops.pointnet2.pointnet2_stack import pointnet2_utils
    pointnet2_utils.ball_query, pointnet2_utils.grouping_operation = ball_query, grouping_operation
    pointnet2_utils.farthest_point_sample = pointnet2_utils.furthest_point_sample = fps


def build(root: Path):
    """PV-RCNN's modules under OpenPCDet's module names, its data-processing and post-processing configs."""
    from pcdet.models.backbones_2d.base_bev_backbone import BaseBEVBackbone
    from pcdet.models.backbones_2d.map_to_bev.height_compression import HeightCompression
    from pcdet.models.backbones_3d.pfe.voxel_set_abstraction import VoxelSetAbstraction
    from pcdet.models.backbones_3d.spconv_backbone import VoxelBackBone8x
    from pcdet.models.backbones_3d.vfe.mean_vfe import MeanVFE
    from pcdet.models.dense_heads.anchor_head_single import AnchorHeadSingle
    from pcdet.models.dense_heads.point_head_simple import PointHeadSimple
    from pcdet.models.roi_heads.pvrcnn_head import PVRCNNHead

    cfg, proc = openpcdet_config(root / "tools" / "cfgs" / "kitti_models" / "pv_rcnn.yaml")
    # as DatasetTemplate: the range a float32 array, the voxel size the config's list
    r, vs, m = np.array(proc.POINT_CLOUD_RANGE, np.float32), list(proc.VOXEL_SIZE), cfg.MODEL
    grid = np.round((r[3:] - r[:3]) / np.array(vs)).astype(np.int64)
    n = len(cfg.CLASS_NAMES)
    net = nn.Module()
    net.register_buffer("global_step", torch.LongTensor(1).zero_())
    net.vfe = MeanVFE(m.VFE, 4)
    net.backbone_3d = VoxelBackBone8x(m.BACKBONE_3D, 4, grid)
    net.map_to_bev_module = HeightCompression(m.MAP_TO_BEV)
    net.pfe = VoxelSetAbstraction(m.PFE, vs, r, num_bev_features=m.MAP_TO_BEV.NUM_BEV_FEATURES,
                                  num_rawpoint_features=4)
    net.backbone_2d = BaseBEVBackbone(m.BACKBONE_2D, m.MAP_TO_BEV.NUM_BEV_FEATURES)
    net.dense_head = AnchorHeadSingle(m.DENSE_HEAD, net.backbone_2d.num_bev_features, n, cfg.CLASS_NAMES, grid, r,
                                      predict_boxes_when_training=True)
    net.point_head = PointHeadSimple(1 if m.POINT_HEAD.CLASS_AGNOSTIC else n, net.pfe.num_point_features_before_fusion,
                                     m.POINT_HEAD)
    net.roi_head = PVRCNNHead(net.pfe.num_point_features, m.ROI_HEAD, num_class=1 if m.ROI_HEAD.CLASS_AGNOSTIC else n)
    return net.eval(), proc, m.POST_PROCESSING, cfg.CLASS_NAMES


MODULES = ("vfe", "backbone_3d", "map_to_bev_module", "pfe", "backbone_2d", "dense_head", "point_head", "roi_head")


def in_range(points: np.ndarray, proc) -> np.ndarray:
    """``mask_points_by_range``: x and y within the range, ends included."""
    r = np.float32(proc.POINT_CLOUD_RANGE)
    keep = (points[:, 0] >= r[0]) & (points[:, 0] <= r[3]) & (points[:, 1] >= r[1]) & (points[:, 1] <= r[4])
    return points[keep]


def ball_margin(net, rois: torch.Tensor, keypoints: np.ndarray) -> float:
    """The smallest | distance - radius | (m) over the (RoI grid point, keypoint) pairs whose side of the
    ball's surface can change what the ball query returns: every keypoint up to the ball's ``nsample``-th
    neighbour in index order."""
    pool = net.roi_head.model_cfg.ROI_GRID_POOL
    with torch.no_grad():
        points = net.roi_head.get_global_grid_points_of_roi(rois, pool.GRID_SIZE)[0].reshape(-1, 3).double().numpy()
    kp = keypoints.astype(np.float64)
    margin = np.inf
    for radius, nsample in zip(pool.POOL_RADIUS, pool.NSAMPLE):
        for lo in range(0, len(points), 2048):
            d = np.linalg.norm(points[lo:lo + 2048, None, :] - kp[None], axis=2)  # (m, P)
            inside = d < radius
            count = np.cumsum(inside, axis=1)
            reach = count - inside <= nsample - 1  # keypoints before the ball is full
            margin = min(margin, float(np.abs(d - radius)[reach].min()))
    return margin


def sorted_levels(levels: dict) -> dict:
    """The multi-scale sparse features of the strided convs (x_conv2..4) with their voxels in ascending
    (batch, z, y, x) order: spconv 2.3.8 leaves them in a hash table's order (on CPU its map's, on GPU its
    direct table's, which atomics fill; ``unique`` sorted them in older releases), and the ball queries of
    the set abstraction group the first voxels of a ball in that order. x_conv1 (submanifold) keeps the
    voxelizer's order, the points' first-seen order."""
    out = dict(levels)
    for name, x in levels.items():
        if name == "x_conv1":
            continue
        idx = x.indices.long()
        key = ((idx[:, 0] * x.spatial_shape[0] + idx[:, 1]) * x.spatial_shape[1] + idx[:, 2]) * x.spatial_shape[2] + idx[:, 3]
        order = torch.argsort(key)
        out[name] = types.SimpleNamespace(indices=x.indices[order], features=x.features[order],
                                          spatial_shape=x.spatial_shape)
    return out


def run(net, proc, post, points: np.ndarray, native_order: bool = False) -> dict:
    """The reference forward on one frame: intermediates, proposals, RCNN outputs and final boxes (the sparse
    levels in sorted order unless ``native_order``: :func:`sorted_levels`)."""
    from pcdet.models.model_utils import model_nms_utils

    raw = in_range(points, proc)
    batch = voxelize(points, proc)
    batch["points"] = torch.from_numpy(np.pad(raw, ((0, 0), (1, 0))))  # (N, 5) batch index, x, y, z, intensity
    seen = {}
    STATS["fps_ties"] = 0
    with torch.no_grad():
        for name in MODULES:
            if name == "roi_head":  # the RPN's outputs, before the RoI head replaces them
                seen["cls"] = batch["batch_cls_preds"][0].clone()
                seen["rpn_boxes"] = batch["batch_box_preds"][0].clone()
            batch = getattr(net, name)(batch)
            if name == "backbone_3d" and not native_order:
                batch["multi_scale_3d_features"] = sorted_levels(batch["multi_scale_3d_features"])
        rcnn_cls, boxes = batch["batch_cls_preds"][0], batch["batch_box_preds"][0]  # (K, 1) logits, (K, 7)
        scores = torch.sigmoid(rcnn_cls).max(dim=-1).values
        selected, selected_scores = model_nms_utils.class_agnostic_nms(scores, boxes, post.NMS_CONFIG,
                                                                       post.SCORE_THRESH)
    keypoints = batch["point_coords"][:, 1:4].numpy()
    # the keypoints are in-range points: their indices (the first match: the frame holds no duplicate point)
    index = np.array([np.flatnonzero((raw[:, :3] == k).all(1))[0] for k in keypoints], np.int32)
    rpn_scores = seen["cls"].max(dim=1).values.numpy()
    proposal_nms = net.roi_head.model_cfg.NMS_CONFIG.TEST
    passed = np.flatnonzero(scores.numpy() >= post.SCORE_THRESH)
    why = (order_free(rpn_scores, seen["rpn_boxes"].numpy(), proposal_nms)
           or order_free(scores.numpy()[passed], boxes.numpy()[passed], post.NMS_CONFIG)
           or capped_tie(scores.numpy(), selected.numpy(), post.NMS_CONFIG.NMS_POST_MAXSIZE)
           or capped_tie(rpn_scores, np.flatnonzero(rpn_scores == batch["roi_scores"][0, -1].item()), 1))
    margin = ball_margin(net, batch["rois"][0][selected], keypoints)
    if why is None and margin < BALL_MARGIN:
        why = f"a keypoint {margin:.1e} m from a RoI grid ball's surface"
    if why is not None and not native_order:
        raise TieError(why)
    return {"num_voxels": batch["voxel_coords"].shape[0], "bev": batch["spatial_features"][0], "cls": seen["cls"],
            "before": batch["point_features_before_fusion"], "fused": batch["point_features"],
            "weights": batch["point_cls_scores"].numpy(), "keypoint_index": index, "fps_ties": STATS["fps_ties"],
            "ball_margin": margin, "rois": batch["rois"][0].numpy(), "roi_scores": batch["roi_scores"][0].numpy(),
            "roi_labels": batch["roi_labels"][0].numpy() - 1, "rcnn_cls": rcnn_cls[:, 0].numpy(),
            "rcnn_boxes": boxes.numpy(), "boxes": boxes[selected].numpy(), "scores": selected_scores.numpy(),
            "labels": batch["roi_labels"][0][selected].numpy() - 1}


def golden(root: Path, out: Path, seed: int = SEED) -> Path:
    net, proc, post, classes = build(root)
    weights = seeded(net, seed, CLS_BIAS, rule=RULE)
    points = frame(seed)
    res = repeatable(run, net, proc, post, points)
    sampled = sampled_entries(res, ("bev", "cls", "before", "fused"), seed + 1)
    path = out / "openpcdet_pv_rcnn.npz"
    np.savez_compressed(path, **weights, points=points, **sampled,
                        **{k: res[k] for k in ("num_voxels", "keypoint_index", "fps_ties", "ball_margin", "weights",
                                               *TWO_STAGE)}, classes=np.array(classes))
    print(f"{path}: {res['num_voxels']} voxels, {len(res['keypoint_index'])} keypoints ({res['fps_ties']} FPS ties), "
          f"{two_stage_counts(res)}; RoI grid ball margin {res['ball_margin']:.2e} m")
    return path


def main(argv=None) -> int:
    return reference_main(argv, __doc__.splitlines()[0], import_pvrcnn, golden, SEED)


if __name__ == "__main__":
    sys.exit(main())
