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

``IGNORED`` names are bookkeeping, not weights (OpenPCDet's ``global_step``).
Sources: OpenPCDet ``tools/cfgs/kitti_models/{pointpillar,second}.yaml`` (``PillarVFE``,
``VoxelBackBone8x``, ``BaseBEVBackbone``, ``AnchorHeadSingle``); MMDetection3D 1.4
``configs/dynamic_voxelization/second_dv_secfpn_8xb2-cosine-80e_kitti-3d-3class.py``
(``SparseEncoder``, ``SECOND``, ``SECONDFPN``, ``Anchor3DHead``).
"""
from __future__ import annotations

COPY, SPARSE = "copy", "sparse"
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
    ("mmdet3d", "dv_second"): _MMDET3D_ENCODER,
}
CONFIG_FILES = {
    ("openpcdet", "pointpillars"): "OpenPCDet tools/cfgs/kitti_models/pointpillar.yaml",
    ("openpcdet", "second"): "OpenPCDet tools/cfgs/kitti_models/second.yaml",
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
