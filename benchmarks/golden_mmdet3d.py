"""Golden data of MMDetection3D's DV-SECOND (KITTI 3-class and Car), made by MMDetection3D's own code.

    PYTHONPATH=MMPKGS:SPCONV python -m benchmarks.golden_mmdet3d --mmdet3d PATH/mmdetection3d \
        [--config 3class|car] [--out tests/golden]

needs mmengine, mmcv-lite (no compiled ops), mmdet 3.x and spconv 2.x (CPU; 2.3.8 with the cumm
0.7.x it requires: with cumm 0.5 its strided convs return no voxels) importable next to this
project's torch, and a source checkout of MMDetection3D 1.4 (never built or installed: its
package is imported from the checkout). mmcv-lite lacks ``mmcv._ext``; a stand-in module gives
the three kernels this network calls, on CPU, with the compiled kernels' contracts
(``mmcv/ops/csrc``): ``dynamic_voxelize_forward`` (float32 floor((p - lo) / size), -1 outside
the grid), ``dynamic_point_to_voxel_forward`` (sorted unique voxels, feature mean) and
``nms_rotated`` (greedy, IoU >= threshold suppresses, exact rotated-rectangle IoU from shapely).
Everything else is MMDetection3D's: the detector is built by its registry from
``configs/dynamic_voxelization/second_dv_secfpn_8xb2-cosine-80e_kitti-3d-3class.py`` (or the Car
config ``second_dv_secfpn_8xb6-80e_kitti-3d-car.py``), its
checkpoint tensors are filled by the seeded rule of ``benchmarks.golden_weights`` and loaded
through its spconv 2.x loader (``_metadata`` version 2, as a published 1.4 file), the frame goes
through ``LiDARPoints.in_range_3d`` (the test pipeline's ``PointsRangeFilter``) and
``model.test_step``. It writes ``tests/golden/mmdet3d_dv_second.npz`` (Car config:
``mmdet3d_dv_second_car.npz``): the rule's seed, the
tensor names and shapes and module versions (no weights), the frame, sampled intermediates (the
bird's-eye map entering the 2D backbone, the class logits) and the final boxes of every class
(gravity centre, our box row) with labels and scores. ``tests/models/test_published_golden_mmdet3d.py``
rebuilds the checkpoint from the rule, imports it and compares.

The reference runs on one thread. spconv 2.3.8's CPU convolution (gather, ``torch.mm``,
``SpconvOps.scatter_add_cpu`` per kernel offset) sums wrongly when OpenMP runs its scatter-add on
more than one thread: on 2 threads a few rows of 7,000 distinct output rows came out wrong on
about half the calls (off by up to 5, where ``index_add`` agrees exactly on one thread), so the
sparse encoder's output changed from call to call (up to 0.35 on the bird's-eye map, 31 or 32
Car boxes). On one thread the convolution equals a float64 sum over its own index pairs to 1e-7
and repeats exactly; ``golden`` runs the test step twice and writes nothing unless the two agree
bit for bit.
"""
from __future__ import annotations

import argparse
import sys
import types
from pathlib import Path

import numpy as np
import torch

from benchmarks.golden_published import frame, iou, polygon, sample
from benchmarks.golden_weights import RULE, fill

# name -> (config file, golden file, weight seed, class-logit bias)
CONFIGS = {
    "3class": ("configs/dynamic_voxelization/second_dv_secfpn_8xb2-cosine-80e_kitti-3d-3class.py",
               "mmdet3d_dv_second.npz", 304, -3.0),  # 50 boxes: 31 Car, 17 Pedestrian, 2 Cyclist
    "car": ("configs/dynamic_voxelization/second_dv_secfpn_8xb6-80e_kitti-3d-car.py",
            "mmdet3d_dv_second_car.npz", 304, -2.5),  # 42 boxes, all Car
}


def dynamic_voxelize_forward(points, voxel_size, coors_range, coors, NDim=3):
    """mmcv's kernel: coors (N, 3) int32 = (z, y, x) cell of each point, -1 where any axis is out."""
    size, lo = voxel_size.float().numpy(), coors_range.float().numpy()
    grid = np.round((lo[NDim:] - lo[:NDim]) / size).astype(np.int64)  # (3,) x, y, z cells
    cell = np.floor((points[:, :NDim].float().numpy() - lo[:NDim]) / size).astype(np.int64)  # float32 math
    bad = ((cell < 0) | (cell >= grid)).any(1)
    cell[bad] = -1
    coors.copy_(torch.from_numpy(cell[:, ::-1].copy()).int())


def dynamic_point_to_voxel_forward(feats, coors, reduce_type):
    """mmcv's kernel (mean): voxels sorted by coordinate (``unique_dim``), points with a -1 dropped."""
    assert reduce_type == "mean", reduce_type
    clean = coors.masked_fill(coors.lt(0).any(-1, True), -1)
    out, inverse, count = torch.unique(clean, sorted=True, return_inverse=True, return_counts=True, dim=0)
    if out[0, 0] < 0:
        out, count, inverse = out[1:], count[1:], inverse - 1
    valid = inverse >= 0
    sums = feats.new_zeros(len(out), feats.shape[1]).index_add_(0, inverse[valid], feats[valid])
    return sums / count[:, None].to(feats.dtype), out, inverse.int(), count.int()


def nms_rotated(dets, scores, order, dets_sorted, labels, iou_threshold, multi_label):
    """mmcv's CPU kernel: boxes (N, 5) [x, y, w, h, angle], greedy by score, IoU >= threshold suppresses."""
    assert not multi_label
    rank = scores.sort(0, descending=True)[1]
    b = dets.double().numpy()
    polys = [polygon(np.r_[r[:2], 0.0, r[2:4], 1.0, r[4]]) for r in b]  # polygon takes 7-value rows
    keep, dropped = [], set()
    for n, i in enumerate(rank.tolist()):
        if i in dropped:
            continue
        keep.append(i)
        dropped.update(j for j in rank[n + 1:].tolist()
                       if j not in dropped and iou(polys[i], polys[j]) >= iou_threshold)
    return torch.tensor(keep, dtype=torch.long)


class _Ext(types.ModuleType):
    """``mmcv._ext``: the three kernels above; any other kernel fails when called."""

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)

        def missing(*args, **kwargs):
            raise NotImplementedError(f"mmcv._ext.{name} has no CPU stand-in")
        return missing


def import_mmdet3d(root: Path) -> None:
    ext = _Ext("mmcv._ext")
    for fn in (dynamic_voxelize_forward, dynamic_point_to_voxel_forward, nms_rotated):
        setattr(ext, fn.__name__, fn)
    sys.modules["mmcv._ext"] = ext
    sys.path.insert(0, str(root))
    import mmdet3d.models  # noqa: F401  registers the detector's modules (the data set and metric packages need
    # nuScenes' and Lyft's toolkits, which building a model does not)
    from mmengine.registry import DefaultScope
    DefaultScope.get_instance("golden_mmdet3d", scope_name="mmdet3d")


def build(root: Path, config: str):
    """MMDetection3D's detector of a config file, in eval mode."""
    from mmengine.config import Config
    from mmdet3d.registry import MODELS
    cfg = Config.fromfile(str(root / config))
    return MODELS.build(cfg.model).eval(), cfg


def run(model, cfg, points: np.ndarray) -> dict:
    """The reference's test step on one frame: intermediates and final boxes (gravity centres)."""
    from mmdet3d.structures import Det3DDataSample, LiDARInstance3DBoxes
    from mmdet3d.structures.points import LiDARPoints

    seen = {}
    hooks = [model.middle_encoder.register_forward_hook(lambda m, i, o: seen.__setitem__("bev", o)),
             model.bbox_head.conv_cls.register_forward_hook(lambda m, i, o: seen.__setitem__("cls", o))]
    pts = LiDARPoints(torch.from_numpy(points), points_dim=4)
    pts = pts[pts.in_range_3d(cfg.point_cloud_range)].tensor  # the test pipeline's PointsRangeFilter
    sample_in = Det3DDataSample(metainfo={"box_type_3d": LiDARInstance3DBoxes, "box_mode_3d": 0,
                                          "sample_idx": 0, "lidar_path": "golden"})
    with torch.no_grad():
        out = model.test_step({"inputs": {"points": [pts]}, "data_samples": [sample_in]})[0].pred_instances_3d
    for h in hooks:
        h.remove()
    box = out.bboxes_3d
    rows = torch.cat([box.gravity_center, box.tensor[:, 3:7]], dim=1)  # (M, 7) x, y, z centre, l, w, h, yaw
    n = model.bbox_head.num_classes
    return {"num_points": len(pts), "bev": seen["bev"][0], "cls": seen["cls"][0].permute(1, 2, 0).reshape(-1, n),
            "boxes": rows.numpy(), "scores": out.scores_3d.numpy(), "labels": out.labels_3d.numpy()}


def golden(root: Path, out: Path, which: str = "3class") -> Path:
    config, name, seed, cls_bias = CONFIGS[which]
    model, cfg = build(root, config)
    state = model.state_dict()
    names, shapes = list(state), [tuple(t.shape) for t in state.values()]
    meta = state._metadata
    values = fill(names, shapes, seed, cls_bias)
    ckpt = type(state)((n, torch.from_numpy(v)) for n, v in values.items())
    ckpt._metadata = meta  # spconv 2.x layout: version 2 on every sparse module, as a published 1.4 file
    model.load_state_dict(ckpt, strict=True)
    points = frame(seed)
    torch.set_num_threads(1)  # spconv's CPU scatter-add races on more threads (module docstring)
    res, again = run(model, cfg, points), run(model, cfg, points)
    differ = [k for k in res if not np.array_equal(np.asarray(res[k]), np.asarray(again[k]))]
    if differ:
        raise RuntimeError(f"two runs of the reference differ in {', '.join(differ)}: no golden data written")
    rng = np.random.Generator(np.random.PCG64(seed + 1))
    bev_idx, bev_val = sample(res["bev"], rng)
    cls_idx, cls_val = sample(res["cls"], rng)
    path = out / name
    versions = [-1 if (meta[k] or {}).get("version") is None else int(meta[k]["version"]) for k in meta]
    np.savez_compressed(path, rule=RULE, seed=seed, cls_bias=cls_bias, names=np.array(names),
                        shape_dims=np.array([len(s) for s in shapes]), shape_values=np.array([d for s in shapes for d in s]),
                        meta_keys=np.array(list(meta)), meta_versions=np.array(versions), points=points,
                        num_points=res["num_points"], bev_index=bev_idx, bev_value=bev_val, cls_index=cls_idx,
                        cls_value=cls_val, boxes=res["boxes"], scores=res["scores"], labels=res["labels"],
                        classes=np.array(cfg.class_names))
    car = int((res["labels"] == list(cfg.class_names).index("Car")).sum())
    print(f"{path}: {res['num_points']} points in range, {len(res['boxes'])} boxes ({car} Car)")
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mmdet3d", type=Path, required=True, help="a source checkout of MMDetection3D 1.4")
    p.add_argument("--config", choices=list(CONFIGS), default="3class")
    p.add_argument("--out", type=Path, default=Path("tests/golden"))
    a = p.parse_args(argv)
    import_mmdet3d(a.mmdet3d)
    a.out.mkdir(parents=True, exist_ok=True)
    golden(a.mmdet3d, a.out, a.config)
    return 0


if __name__ == "__main__":
    sys.exit(main())
