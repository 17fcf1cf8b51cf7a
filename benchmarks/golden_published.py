"""Golden data of the published networks, made by the reference implementation itself.

    python -m benchmarks.golden_published --openpcdet PATH/OpenPCDet [--out tests/golden]

needs spconv 2.x (``pip install spconv``, CPU) and easydict importable next to this project's
torch, and a source checkout of OpenPCDet (never built: its pure-torch modules are imported from
their files; the CUDA-only rotated NMS is replaced by a CPU stand-in, greedy NMS over the exact
BEV IoU of the rotated rectangles from shapely). For each network it builds the reference's own
modules from its config file, fills their checkpoint tensors by the seeded rule of
``benchmarks.golden_weights`` (every BatchNorm statistic random), runs one frame, and writes
``tests/golden/<source>_<model>.npz``: the rule's seed and the tensor names and shapes (no
weights), the frame, sampled intermediate tensors (BEV map, class logits) and the final boxes of
every class with their labels and scores. ``tests/models/test_published_golden.py`` rebuilds the
checkpoint from the rule, imports it and compares.
"""
from __future__ import annotations

import argparse
import os
import sys
import types
from pathlib import Path

import numpy as np
import torch
from torch import nn

from benchmarks.golden_weights import RULE, fill

# config, seed, class-logit bias, dense-head weight scale (PointPillars: 281 anchors score above 0.1)
MODELS = {"pointpillars": ("pointpillar.yaml", 101, -4.0, 0.1), "second": ("second.yaml", 202, -1.0, 1.0)}
SAMPLES = 256  # sampled entries of each intermediate tensor


def frame(seed: int) -> np.ndarray:
    """(N, 4) float32 points: a ground plane, four car-sized boxes' surfaces ahead at 15 to 60 m and
    a few points outside the range (x < 0, above 1 m)."""
    rng = np.random.Generator(np.random.PCG64(seed))
    ground = np.c_[rng.uniform(0, 70, 6000), rng.uniform(-38, 38, 6000), rng.normal(-1.75, 0.03, 6000)]
    cars = []
    for x, y, yaw in ((15.0, -3.5, 0.1), (30.0, 0.2, -0.05), (46.0, 3.6, 1.5), (60.0, -0.4, 3.0)):
        local = rng.uniform(-0.5, 0.5, (500, 3)) * (4.2, 1.8, 1.5)
        face = rng.integers(0, 3, 500)
        local[np.arange(500), face] = np.sign(local[np.arange(500), face]) * np.array((2.1, 0.9, 0.75))[face]
        c, s = np.cos(yaw), np.sin(yaw)
        cars.append(np.c_[x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1],
                          -1.0 + local[:, 2]])
    outside = np.c_[rng.uniform(-10, 0, 200), rng.uniform(-20, 20, 200), rng.uniform(1.2, 3, 200)]
    xyz = np.concatenate([ground, *cars, outside])
    return np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype(np.float32)


def import_openpcdet(root: Path):
    """The reference modules, imported from their files without running the packages' __init__ (which
    import every detector and the compiled CUDA ops)."""
    for name in ("pcdet", "pcdet.models", "pcdet.models.backbones_2d", "pcdet.models.backbones_3d",
                 "pcdet.models.backbones_3d.vfe", "pcdet.models.backbones_2d.map_to_bev", "pcdet.models.dense_heads",
                 "pcdet.models.model_utils", "pcdet.utils", "pcdet.ops", "pcdet.ops.iou3d_nms",
                 "pcdet.ops.roiaware_pool3d", "pcdet.models.dense_heads.target_assigner"):
        module = types.ModuleType(name)
        module.__path__ = [os.path.join(root, *name.split("."))]
        sys.modules[name] = module
    for name in ("pcdet.ops.iou3d_nms.iou3d_nms_cuda", "pcdet.ops.roiaware_pool3d.roiaware_pool3d_cuda", "SharedArray"):
        sys.modules[name] = types.ModuleType(name)
    sys.path.insert(0, str(root))
    torch.Tensor.cuda = lambda self, *a, **k: self  # the anchor generator moves its anchors to the GPU
    from pcdet.ops.iou3d_nms import iou3d_nms_utils
    iou3d_nms_utils.nms_gpu = cpu_nms


def polygon(box: np.ndarray):
    """The BEV rectangle of a box [x, y, z, dx, dy, dz, heading] (a shapely polygon)."""
    from shapely.geometry import Polygon

    c, s = np.cos(box[6]), np.sin(box[6])
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * box[3:5] / 2
    return Polygon(corners @ np.array([[c, s], [-s, c]]) + box[:2])


def cpu_nms(boxes, scores, thresh, pre_maxsize=None, **kwargs):
    """Stand-in for OpenPCDet's CUDA ``nms_gpu`` (same contract): greedy in score order, a box is
    dropped when its exact rotated BEV IoU (shapely) with a kept box is > thresh. Only kept boxes whose
    circumscribed circles meet the candidate's are measured (IoU 0 otherwise), found with numpy."""
    order = scores.sort(0, descending=True)[1]
    if pre_maxsize is not None:
        order = order[:pre_maxsize]
    b = boxes[order].double().numpy()  # (M, 7)
    radius = np.hypot(b[:, 3], b[:, 4]) / 2  # (M,) m
    polys = [polygon(box) for box in b]
    keep = []
    for i in range(len(b)):
        k = np.array(keep, dtype=np.int64)
        near = k[np.hypot(*(b[k, :2] - b[i, :2]).T) <= radius[k] + radius[i]]
        if all(iou(polys[j], polys[i]) <= thresh for j in near):
            keep.append(i)
    return order[torch.tensor(keep, dtype=torch.long)], None


def iou(a, b) -> float:
    """IoU of two shapely polygons."""
    inter = a.intersection(b).area
    return inter / max(a.area + b.area - inter, 1e-8)


def voxelize(points: np.ndarray, cfg) -> dict:
    """OpenPCDet's test-time data processing: mask_points_by_range, then spconv's Point2VoxelCPU3d."""
    from cumm import tensorview as tv
    from spconv.utils import Point2VoxelCPU3d

    r = cfg.POINT_CLOUD_RANGE
    keep = (points[:, 0] >= r[0]) & (points[:, 0] <= r[3]) & (points[:, 1] >= r[1]) & (points[:, 1] <= r[4])
    inside = points[keep]
    cells = np.floor((inside[:, :3] - np.float32(r[:3])) / np.float32(cfg.VOXEL_SIZE)).astype(np.int64)
    grid = np.round((np.array(r[3:]) - r[:3]) / cfg.VOXEL_SIZE).astype(np.int64)
    distinct = len(np.unique(cells[((cells >= 0) & (cells < grid)).all(1)], axis=0))
    for _ in range(20):  # spconv 2.3.8's CPU voxelizer sometimes drops voxels (7914 / 7915 / 7916 of 7916
        # distinct ones in three calls on the same points): keep a call that found every occupied cell
        gen = Point2VoxelCPU3d(vsize_xyz=cfg.VOXEL_SIZE, coors_range_xyz=r, num_point_features=4,
                               max_num_points_per_voxel=cfg.MAX_POINTS_PER_VOXEL, max_num_voxels=cfg.MAX_NUMBER_OF_VOXELS)
        voxels, coords, num = (t.numpy().copy() for t in gen.point_to_voxel(tv.from_numpy(inside)))
        if len(coords) == min(distinct, cfg.MAX_NUMBER_OF_VOXELS):
            break
    else:
        raise RuntimeError(f"spconv's voxelizer never found all {distinct} occupied cells")
    return {"voxels": torch.from_numpy(voxels), "voxel_num_points": torch.from_numpy(num),
            "voxel_coords": torch.from_numpy(np.pad(coords, ((0, 0), (1, 0)))).int(), "batch_size": 1}


def openpcdet_config(cfg_path: Path):
    """(cfg, proc) of an OpenPCDet model config: the config with the data set config it extends merged in, and
    the voxelisation settings of its test-time data processor."""
    import yaml
    from easydict import EasyDict
    cfg = EasyDict(yaml.safe_load(cfg_path.read_text()))
    base = EasyDict(yaml.safe_load((cfg_path.parents[2] / cfg.DATA_CONFIG._BASE_CONFIG_).read_text()))
    cfg.DATA_CONFIG = EasyDict({**base, **cfg.DATA_CONFIG})  # the data set config the model's extends
    data = {d["NAME"]: d for d in cfg.DATA_CONFIG.DATA_PROCESSOR}["transform_points_to_voxels"]
    proc = EasyDict(POINT_CLOUD_RANGE=cfg.DATA_CONFIG.POINT_CLOUD_RANGE, VOXEL_SIZE=data.VOXEL_SIZE,
                    MAX_POINTS_PER_VOXEL=data.MAX_POINTS_PER_VOXEL, MAX_NUMBER_OF_VOXELS=data.MAX_NUMBER_OF_VOXELS.test)
    return cfg, proc


def build(cfg_path: Path):
    """The reference detector's modules under OpenPCDet's own module names, and its configs."""
    from pcdet.models.backbones_2d.base_bev_backbone import BaseBEVBackbone
    from pcdet.models.backbones_2d.map_to_bev.height_compression import HeightCompression
    from pcdet.models.backbones_2d.map_to_bev.pointpillar_scatter import PointPillarScatter
    from pcdet.models.backbones_3d.spconv_backbone import VoxelBackBone8x
    from pcdet.models.backbones_3d.vfe.mean_vfe import MeanVFE
    from pcdet.models.backbones_3d.vfe.pillar_vfe import PillarVFE
    from pcdet.models.dense_heads.anchor_head_single import AnchorHeadSingle

    cfg, proc = openpcdet_config(cfg_path)
    r, vs, m = np.array(proc.POINT_CLOUD_RANGE), np.array(proc.VOXEL_SIZE), cfg.MODEL
    grid = np.round((r[3:] - r[:3]) / vs).astype(np.int64)
    net = nn.Module()
    net.register_buffer("global_step", torch.LongTensor(1).zero_())
    if m.VFE.NAME == "PillarVFE":
        net.vfe = PillarVFE(m.VFE, 4, vs, r)
        net.map_to_bev_module = PointPillarScatter(m.MAP_TO_BEV, grid)
        c = m.MAP_TO_BEV.NUM_BEV_FEATURES
    else:
        net.vfe = MeanVFE(m.VFE, 4)
        net.backbone_3d = VoxelBackBone8x(m.BACKBONE_3D, 4, grid)
        net.map_to_bev_module = HeightCompression(m.MAP_TO_BEV)
        c = m.MAP_TO_BEV.NUM_BEV_FEATURES
    net.backbone_2d = BaseBEVBackbone(m.BACKBONE_2D, c)
    net.dense_head = AnchorHeadSingle(m.DENSE_HEAD, net.backbone_2d.num_bev_features, len(cfg.CLASS_NAMES),
                                      cfg.CLASS_NAMES, grid, r, predict_boxes_when_training=False)
    return net.eval(), proc, m.POST_PROCESSING


def run(net, proc, post, points: np.ndarray) -> dict:
    """The reference forward on one frame: intermediates and post-processed boxes."""
    from pcdet.models.model_utils import model_nms_utils

    batch = voxelize(points, proc)
    with torch.no_grad():
        for name in ("vfe", "backbone_3d", "map_to_bev_module", "backbone_2d", "dense_head"):
            if hasattr(net, name):
                batch = getattr(net, name)(batch)
                print(f"{name} done", flush=True)
        scores, labels = torch.max(torch.sigmoid(batch["batch_cls_preds"][0]), dim=-1)  # post_processing, one class per box
        boxes = batch["batch_box_preds"][0]
        selected, selected_scores = model_nms_utils.class_agnostic_nms(scores, boxes, post.NMS_CONFIG,
                                                                       post.SCORE_THRESH)
    return {"num_voxels": batch["voxel_coords"].shape[0], "bev": batch["spatial_features"][0],
            "cls": batch["batch_cls_preds"][0], "boxes": boxes[selected].numpy(), "scores": selected_scores.numpy(),
            "labels": labels[selected].numpy()}


def sample(t: torch.Tensor, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(SAMPLES, ndim) indices of mostly non-zero entries and their values."""
    nz = torch.nonzero(t).numpy()
    pick = nz[rng.choice(len(nz), min(SAMPLES, len(nz)), replace=False)] if len(nz) else np.zeros((0, t.dim()), int)
    return pick.astype(np.int64), t.numpy()[tuple(pick.T)]


def seeded(net: nn.Module, seed: int, cls_bias: float, head_scale: float = 1.0, rule: str = RULE) -> dict:
    """Fill ``net``'s checkpoint tensors by the seeded ``rule``; returns what a golden file records of them
    (the rule, its arguments, the tensor names and shapes; no weights)."""
    state = net.state_dict()
    names, shapes = list(state), [tuple(t.shape) for t in state.values()]
    values = fill(names, shapes, seed, cls_bias, head_scale, rule)
    net.load_state_dict({n: torch.from_numpy(v) for n, v in values.items()})
    return dict(rule=rule, seed=seed, cls_bias=cls_bias, head_scale=head_scale, names=np.array(names),
                shape_dims=np.array([len(s) for s in shapes]), shape_values=np.array([d for s in shapes for d in s]))


def repeatable(run, *args) -> dict:
    """``run(*args)``'s result, run twice on one thread (spconv 2.3.8's CPU scatter-add races on more,
    benchmarks/golden_mmdet3d.py); RuntimeError, and no golden data, when the two runs differ."""
    torch.set_num_threads(1)
    res, again = run(*args), run(*args)
    differ = [k for k in res if not np.array_equal(np.asarray(res[k]), np.asarray(again[k]))]
    if differ:
        raise RuntimeError(f"two runs of the reference differ in {', '.join(differ)}: no golden data written")
    return res


def sampled_entries(res: dict, keys, seed: int) -> dict:
    """``<key>_index`` and ``<key>_value`` of entries of each map ``res[key]`` sampled by ``sample`` (the
    stream ``seed``, in ``keys``' order)."""
    rng = np.random.Generator(np.random.PCG64(seed))
    out = {}
    for key in keys:
        out[f"{key}_index"], out[f"{key}_value"] = sample(res[key], rng)
    return out


# what a two-stage reference's golden file keeps of its result: proposals, the RCNN on them, the final boxes
TWO_STAGE = ("rois", "roi_scores", "roi_labels", "rcnn_cls", "rcnn_boxes", "boxes", "scores", "labels")


def two_stage_counts(res: dict) -> str:
    """The proposals and final boxes of a two-stage reference's result, with their Car ones (label 0)."""
    return (f"{len(res['rois'])} proposals ({int((res['roi_labels'] == 0).sum())} Car), {len(res['boxes'])} boxes "
            f"({int((res['labels'] == 0).sum())} Car)")


def reference_main(argv, description: str, importer, make, seed: int) -> int:
    """The command line of a one-network generator: ``--openpcdet`` checkout, ``--out`` folder, ``--seed``;
    ``importer(root)`` makes OpenPCDet's modules importable, ``make(root, out, seed)`` writes the file."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--openpcdet", type=Path, required=True, help="a source checkout of OpenPCDet")
    p.add_argument("--out", type=Path, default=Path("tests/golden"))
    p.add_argument("--seed", type=int, default=seed, help="weight rule and frame seed")
    a = p.parse_args(argv)
    importer(a.openpcdet)
    a.out.mkdir(parents=True, exist_ok=True)
    make(a.openpcdet, a.out, a.seed)
    return 0


def golden(root: Path, model: str, out: Path) -> Path:
    cfg_file, seed, cls_bias, head_scale = MODELS[model]
    net, proc, post = build(root / "tools" / "cfgs" / "kitti_models" / cfg_file)
    weights = seeded(net, seed, cls_bias, head_scale)
    points = frame(seed)
    torch.set_num_threads(1)  # spconv 2.3.8's CPU scatter-add races on more threads (benchmarks/golden_mmdet3d.py)
    res = run(net, proc, post, points)
    rng = np.random.Generator(np.random.PCG64(seed + 1))
    bev_idx, bev_val = sample(res["bev"], rng)
    cls_idx, cls_val = sample(res["cls"], rng)
    path = out / f"openpcdet_{model}.npz"
    np.savez_compressed(path, **weights, points=points, num_voxels=res["num_voxels"], bev_index=bev_idx, bev_value=bev_val,
                        cls_index=cls_idx, cls_value=cls_val, boxes=res["boxes"], scores=res["scores"],
                        labels=res["labels"], classes=np.array(["Car", "Pedestrian", "Cyclist"]))
    print(f"{path}: {res['num_voxels']} voxels, {len(res['boxes'])} boxes "
          f"({int((res['labels'] == 0).sum())} Car)")
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--openpcdet", type=Path, required=True, help="a source checkout of OpenPCDet")
    p.add_argument("--out", type=Path, default=Path("tests/golden"))
    p.add_argument("--models", default=",".join(MODELS))
    a = p.parse_args(argv)
    import_openpcdet(a.openpcdet)
    a.out.mkdir(parents=True, exist_ok=True)
    for model in a.models.split(","):
        golden(a.openpcdet, model, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
