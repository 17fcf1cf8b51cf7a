"""The tensor names and shapes of the published checkpoints, written out from the references'
module definitions (OpenPCDet PillarVFE / BaseBEVBackbone / VoxelBackBone8x / AnchorHeadSingle,
MMDetection3D SparseEncoder / SECOND / SECONDFPN / Anchor3DHead), for tests that build a file in
the published layout with random values."""
from __future__ import annotations

BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def _bn(prefix: str, c: int) -> dict:
    return {f"{prefix}.{p}": (() if p == "num_batches_tracked" else (c,)) for p in BN}


def bev_2d(prefix: str, c_in: int, layers, filters, ups, up_filters, zero_pad: bool, deblocks: str) -> dict:
    """BaseBEVBackbone (zero_pad: a ZeroPad2d first) / MMDetection3D SECOND + SECONDFPN."""
    out, first = {}, 1 if zero_pad else 0
    for i, (n, f) in enumerate(zip(layers, filters)):
        c = c_in if i == 0 else filters[i - 1]
        for j in range(n + 1):
            at = first + 3 * j
            out[f"{prefix}.blocks.{i}.{at}.weight"] = (f, c if j == 0 else f, 3, 3)
            out.update(_bn(f"{prefix}.blocks.{i}.{at + 1}", f))
        out[f"{deblocks}.{i}.0.weight"] = (f, up_filters[i], ups[i], ups[i])
        out.update(_bn(f"{deblocks}.{i}.1", up_filters[i]))
    return out


def head(prefix: str, c: int, box: str) -> dict:
    return {f"{prefix}.conv_cls.weight": (18, c, 1, 1), f"{prefix}.conv_cls.bias": (18,),
            f"{prefix}.{box}.weight": (42, c, 1, 1), f"{prefix}.{box}.bias": (42,),
            f"{prefix}.conv_dir_cls.weight": (12, c, 1, 1), f"{prefix}.conv_dir_cls.bias": (12,)}


def sparse_shape(k, c_in, c_out, v2: bool) -> tuple:
    return (c_out, *k, c_in) if v2 else (*k, c_in, c_out)


def encoder(names, v2: bool) -> dict:
    """VoxelBackBone8x / SparseEncoder: (conv name, bn name, kernel, c_in, c_out) in order."""
    out = {}
    for conv, bn, k, ci, co in names:
        out[conv] = sparse_shape(k, ci, co, v2)
        out.update(_bn(bn, co))
    return out


def openpcdet_pointpillars() -> dict:
    out = {"vfe.pfn_layers.0.linear.weight": (64, 10), **_bn("vfe.pfn_layers.0.norm", 64)}
    out.update(bev_2d("backbone_2d", 64, (3, 5, 5), (64, 128, 256), (1, 2, 4), (128, 128, 128), True,
                      "backbone_2d.deblocks"))
    out.update(head("dense_head", 384, "conv_box"))
    out["global_step"] = (1,)
    return out


def openpcdet_second(v2: bool) -> dict:
    names = [("backbone_3d.conv_input.0.weight", "backbone_3d.conv_input.1", (3, 3, 3), 4, 16),
             ("backbone_3d.conv1.0.0.weight", "backbone_3d.conv1.0.1", (3, 3, 3), 16, 16)]
    chans = {2: (16, 32), 3: (32, 64), 4: (64, 64)}
    for i, (ci, co) in chans.items():
        for j in range(3):
            names.append((f"backbone_3d.conv{i}.{j}.0.weight", f"backbone_3d.conv{i}.{j}.1", (3, 3, 3),
                          ci if j == 0 else co, co))
    names.append(("backbone_3d.conv_out.0.weight", "backbone_3d.conv_out.1", (3, 1, 1), 64, 128))
    out = encoder(names, v2)
    out.update(bev_2d("backbone_2d", 256, (5, 5), (128, 256), (1, 2), (256, 256), True, "backbone_2d.deblocks"))
    out.update(head("dense_head", 512, "conv_box"))
    out["global_step"] = (1,)
    return out


def mmdet3d_dv_second(v2: bool) -> dict:
    m = "middle_encoder"
    names = [(f"{m}.conv_input.0.weight", f"{m}.conv_input.1", (3, 3, 3), 4, 16),
             (f"{m}.encoder_layers.encoder_layer1.0.0.weight", f"{m}.encoder_layers.encoder_layer1.0.1", (3, 3, 3), 16, 16)]
    chans = {2: (16, 32), 3: (32, 64), 4: (64, 64)}
    for i, (ci, co) in chans.items():
        for j in range(3):
            p = f"{m}.encoder_layers.encoder_layer{i}.{j}"
            names.append((f"{p}.0.weight", f"{p}.1", (3, 3, 3), ci if j == 0 else co, co))
    names.append((f"{m}.conv_out.0.weight", f"{m}.conv_out.1", (3, 1, 1), 64, 128))
    out = encoder(names, v2)
    out.update(bev_2d("backbone", 256, (5, 5), (128, 256), (1, 2), (256, 256), False, "neck.deblocks"))
    out.update(head("bbox_head", 512, "conv_reg"))
    return out
