"""Where each tensor of a published checkpoint goes in our ``kitti`` profile: the mapping as data.

A rule is ``(pattern, target, shifts, kind)``: ``pattern`` a regular expression over the
reference's tensor name (matched whole), ``target`` our name with the pattern's named groups
(``shifts`` adds a constant to a numeric group: OpenPCDet's 2D blocks start with a ZeroPad2d, so
its layer j is our j - 1), ``kind`` how the tensor is laid out:

- ``COPY``: the same layout (convs, deconvs, BatchNorm, the head's 1x1 convs: both references
  lay the head channels out anchor-major with the classes in their config's order, as ours).
- ``SPARSE``: a sparse-conv weight; spconv 2.x holds ``[out, kD, kH, kW, in]``, spconv 1.x (and
  MMCV's ops) ``[kD, kH, kW, in, out]``; ours is ``(K, in, out)`` with z slowest
  (``harness.import_weights.sparse_weight``).
- ``FC``: a fully connected layer, OpenPCDet's RoI heads' ``Conv1d`` of kernel 1 (``[out, in, 1]``) or its
  set abstractions' ``Conv2d`` of kernel 1 (``[out, in, 1, 1]``) for our ``Linear`` (``[out, in]``); its
  BatchNorm tensors as they are.

``IGNORED`` names are bookkeeping, not weights (OpenPCDet's ``global_step``).
Sources: OpenPCDet ``tools/cfgs/kitti_models/{pointpillar,second,PartA2,pv_rcnn}.yaml`` (``PillarVFE``,
``VoxelBackBone8x``, ``UNetV2``, ``BaseBEVBackbone``, ``AnchorHeadSingle``, ``PointIntraPartOffsetHead``,
``PartA2FCHead``, ``VoxelSetAbstraction``, ``PointHeadSimple``, ``PVRCNNHead``); MMDetection3D 1.4
``configs/dynamic_voxelization/second_dv_secfpn_8xb2-cosine-80e_kitti-3d-3class.py``
(``SparseEncoder``, ``SECOND``, ``SECONDFPN``, ``Anchor3DHead``).
"""
from __future__ import annotations

COPY, SPARSE, FC = "copy", "sparse", "fc"
BN = r"(?P<p>weight|bias|running_mean|running_var|num_batches_tracked)"
CONV = r"(?P<p>weight|bias)"

_OPENPCDET_BEV = [
    (r"backbone_2d\.blocks\.(?P<i>\d+)\.(?P<j>\d+)\.(?P<p>.+)", "backbone2d.blocks.{i}.{j}.{p}", {"j": -1}, COPY),
    (r"backbone_2d\.deblocks\.(?P<i>\d+)\.(?P<j>[01])\.(?P<p>.+)", "backbone2d.ups.{i}.{j}.{p}", {}, COPY),
    (r"dense_head\.conv_(?P<c>cls|box)\." + CONV, "head.conv_{c}.{p}", {}, COPY),
    (r"dense_head\.conv_dir_cls\." + CONV, "head.conv_dir.{p}", {}, COPY),
]

_OPENPCDET_8X = [
    (r"backbone_3d\.conv_input\.0\.weight", "backbone3d.stem.0.0.weight", {}, SPARSE),
    (r"backbone_3d\.conv_input\.1\." + BN, "backbone3d.stem.0.1.norm.{p}", {}, COPY),
    (r"backbone_3d\.conv1\.0\.0\.weight", "backbone3d.stem.1.0.weight", {}, SPARSE),
    (r"backbone_3d\.conv1\.0\.1\." + BN, "backbone3d.stem.1.1.norm.{p}", {}, COPY),
    (r"backbone_3d\.conv(?P<i>[234])\.(?P<j>\d+)\.0\.weight", "backbone3d.stages.{i}.{j}.0.weight", {"i": -2}, SPARSE),
    (r"backbone_3d\.conv(?P<i>[234])\.(?P<j>\d+)\.1\." + BN, "backbone3d.stages.{i}.{j}.1.norm.{p}", {"i": -2}, COPY),
    (r"backbone_3d\.conv_out\.0\.weight", "backbone3d.out.0.weight", {}, SPARSE),
    (r"backbone_3d\.conv_out\.1\." + BN, "backbone3d.out.1.norm.{p}", {}, COPY),
]


def _retarget(rules: list, prefixes: dict[str, str]) -> list:
    """``rules`` with our names' leading ``prefixes`` replaced (a shared table under another module)."""
    def target(t: str) -> str:
        return next((new + t[len(old):] for old, new in prefixes.items() if t.startswith(old)), t)
    return [(p, target(t), s, k) for p, t, s, k in rules]


# OpenPCDet UNetV2's decoder: conv_up_t{i} / conv_up_m{i} at encoder level i - 1 (1 = the stem), inv_conv{i}
# from level i - 1 to i - 2, conv5 at level 0
_OPENPCDET_UNET = [
    (r"backbone_3d\.conv_up_t(?P<i>[1-4])\.conv(?P<j>[12])\.weight", "unet.lateral.{i}.conv{j}.weight", {"i": -1},
     SPARSE),
    (r"backbone_3d\.conv_up_t(?P<i>[1-4])\.bn(?P<j>[12])\." + BN, "unet.lateral.{i}.bn{j}.{p}", {"i": -1}, COPY),
    (r"backbone_3d\.conv_up_m(?P<i>[1-4])\.0\.weight", "unet.merge.{i}.0.weight", {"i": -1}, SPARSE),
    (r"backbone_3d\.conv_up_m(?P<i>[1-4])\.1\." + BN, "unet.merge.{i}.1.norm.{p}", {"i": -1}, COPY),
    (r"backbone_3d\.inv_conv(?P<i>[2-4])\.0\.weight", "unet.up.{i}.weight", {"i": -2}, SPARSE),
    (r"backbone_3d\.inv_conv(?P<i>[2-4])\.1\." + BN, "unet.up_norm.{i}.norm.{p}", {"i": -2}, COPY),
    (r"backbone_3d\.conv5\.0\.0\.weight", "unet.out.0.weight", {}, SPARSE),
    (r"backbone_3d\.conv5\.0\.1\." + BN, "unet.out.1.norm.{p}", {}, COPY),
]

# RoIHeadTemplate's Conv1d(k=1) fc layers: SHARED_FC, then CLS_FC and REG_FC of two layers (index 7 is the output)
_OPENPCDET_RCNN_FC = [
    (r"roi_head\.shared_fc_layer\.(?P<i>\d+)\.(?P<p>.+)", "refine.shared.{i}.{p}", {}, FC),
    (r"roi_head\.(?P<b>cls|reg)_layers\.7\." + CONV, "refine.{b}.{p}", {}, FC),
    (r"roi_head\.(?P<b>cls|reg)_layers\.(?P<i>[0-6])\.(?P<p>.+)", "refine.{b}_fc.{i}.{p}", {}, FC),
]

# Part-A2's point head (CLS_FC, PART_FC empty: one Linear each) and PartA2FCHead: its SubM blocks on the
# pooled grid, then the fc layers
_OPENPCDET_PARTA2_HEADS = [
    (r"point_head\.cls_layers\.0\." + CONV, "seg_head.0.{p}", {}, COPY),
    (r"point_head\.part_reg_layers\.0\." + CONV, "part_head.0.{p}", {}, COPY),
    (r"roi_head\.conv_part\.(?P<j>[01])\.0\.weight", "rcnn.part_branch.{j}.0.weight", {}, SPARSE),
    (r"roi_head\.conv_part\.(?P<j>[01])\.1\." + BN, "rcnn.part_branch.{j}.1.norm.{p}", {}, COPY),
    (r"roi_head\.conv_rpn\.(?P<j>[01])\.0\.weight", "rcnn.feat_branch.{j}.0.weight", {}, SPARSE),
    (r"roi_head\.conv_rpn\.(?P<j>[01])\.1\." + BN, "rcnn.feat_branch.{j}.1.norm.{p}", {}, COPY),
    *_retarget(_OPENPCDET_RCNN_FC, {"refine.": "rcnn.refine."}),
]


def _set_abstraction(pattern: str, target: str) -> list:
    """A StackSAModuleMSG's shared MLPs (Conv2d(k=1), BatchNorm2d, ReLU per layer) onto our SetAbstraction's
    (Linear, BatchNorm, ReLU): ``pattern`` / ``target`` name the module."""
    return [(pattern + r"\.mlps\.(?P<j>\d+)\.(?P<i>\d+)\.weight", target + ".mlps.{j}.{i}.weight", {}, FC),
            (pattern + r"\.mlps\.(?P<j>\d+)\.(?P<i>\d+)\." + BN, target + ".mlps.{j}.{i}.{p}", {}, COPY)]


# PV-RCNN's VoxelSetAbstraction (raw points, x_conv1..4, fusion), PointHeadSimple (the keypoint weights, CLS_FC
# 256-256: Linear, BN, ReLU twice, then Linear) and PVRCNNHead (RoI-grid set abstraction, fc layers)
_OPENPCDET_PVRCNN_HEADS = [
    *_set_abstraction(r"pfe\.SA_rawpoints", "vsa.raw"),
    *_set_abstraction(r"pfe\.SA_layers\.(?P<k>\d+)", "vsa.levels.{k}"),
    (r"pfe\.vsa_point_feature_fusion\.(?P<i>[01])\.(?P<p>.+)", "vsa.fuse.{i}.{p}", {}, COPY),
    (r"point_head\.cls_layers\.(?P<i>\d+)\.(?P<p>.+)", "vsa.weight.{i}.{p}", {}, COPY),
    *_set_abstraction(r"roi_head\.roi_grid_pool_layer", "roi_grid.sa"),
    *_OPENPCDET_RCNN_FC,
]

_MMDET3D_ENCODER = [
    (r"middle_encoder\.conv_input\.0\.weight", "backbone3d.stem.0.0.weight", {}, SPARSE),
    (r"middle_encoder\.conv_input\.1\." + BN, "backbone3d.stem.0.1.norm.{p}", {}, COPY),
    (r"middle_encoder\.encoder_layers\.encoder_layer1\.0\.0\.weight", "backbone3d.stem.1.0.weight", {}, SPARSE),
    (r"middle_encoder\.encoder_layers\.encoder_layer1\.0\.1\." + BN, "backbone3d.stem.1.1.norm.{p}", {}, COPY),
    (r"middle_encoder\.encoder_layers\.encoder_layer(?P<i>[234])\.(?P<j>\d+)\.0\.weight",
     "backbone3d.stages.{i}.{j}.0.weight", {"i": -2}, SPARSE),
    (r"middle_encoder\.encoder_layers\.encoder_layer(?P<i>[234])\.(?P<j>\d+)\.1\." + BN,
     "backbone3d.stages.{i}.{j}.1.norm.{p}", {"i": -2}, COPY),
    (r"middle_encoder\.conv_out\.0\.weight", "backbone3d.out.0.weight", {}, SPARSE),
    (r"middle_encoder\.conv_out\.1\." + BN, "backbone3d.out.1.norm.{p}", {}, COPY),
    (r"backbone\.blocks\.(?P<i>\d+)\.(?P<j>\d+)\.(?P<p>.+)", "backbone2d.blocks.{i}.{j}.{p}", {}, COPY),
    (r"neck\.deblocks\.(?P<i>\d+)\.(?P<j>[01])\.(?P<p>.+)", "backbone2d.ups.{i}.{j}.{p}", {}, COPY),
    (r"bbox_head\.conv_cls\." + CONV, "head.conv_cls.{p}", {}, COPY),
    (r"bbox_head\.conv_reg\." + CONV, "head.conv_box.{p}", {}, COPY),
    (r"bbox_head\.conv_dir_cls\." + CONV, "head.conv_dir.{p}", {}, COPY),
]

# (source, our model name) -> rules; the published config each one reads
TABLES = {
    ("openpcdet", "pointpillars"): [(r"vfe\.pfn_layers\.0\.(?P<m>linear|norm)\.(?P<p>.+)", "vfe.{m}.{p}", {}, COPY)]
    + _OPENPCDET_BEV,
    ("openpcdet", "second"): [*_OPENPCDET_8X, *_OPENPCDET_BEV],
    ("openpcdet", "parta2"): [*_retarget(_OPENPCDET_8X, {"backbone3d.": "unet.encoder."}), *_OPENPCDET_UNET,
                              *_retarget(_OPENPCDET_BEV, {"head.": "rpn."}), *_OPENPCDET_PARTA2_HEADS],
    ("openpcdet", "pv_rcnn"): [*_OPENPCDET_8X, *_retarget(_OPENPCDET_BEV, {"head.": "rpn."}), *_OPENPCDET_PVRCNN_HEADS],
    ("mmdet3d", "dv_second"): _MMDET3D_ENCODER,
}
CONFIG_FILES = {
    ("openpcdet", "pointpillars"): "OpenPCDet tools/cfgs/kitti_models/pointpillar.yaml",
    ("openpcdet", "second"): "OpenPCDet tools/cfgs/kitti_models/second.yaml",
    ("openpcdet", "parta2"): "OpenPCDet tools/cfgs/kitti_models/PartA2.yaml",
    ("openpcdet", "pv_rcnn"): "OpenPCDet tools/cfgs/kitti_models/pv_rcnn.yaml",
    ("mmdet3d", "dv_second"): "MMDetection3D configs/dynamic_voxelization/second_dv_secfpn_8xb2-cosine-80e_kitti-3d-3class.py",
}
# Published configs of the same network for fewer classes: (source, model, the file's classes) -> config.
# Their head keeps those classes' anchor sets (size, bottom height) and heads; everything else is the
# main config's (MMDetection3D's Car config inherits the 3-class model's anchor ranges and test_cfg).
CLASS_CONFIGS = {
    ("mmdet3d", "dv_second", ("Car",)):
        "MMDetection3D configs/dynamic_voxelization/second_dv_secfpn_8xb6-80e_kitti-3d-car.py",
}
IGNORED = {"openpcdet": ("global_step",), "mmdet3d": ()}
