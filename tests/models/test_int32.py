"""Every integer key and linear index of every model's graph fits int32 in every profile.

OpenVINO's CPU plugin computes int64 in int32, so a key beyond 2^31 silently changes its result.
Exporting the kitti-profile graphs takes minutes, so here the bounds come from the configs (the
grid sizes and caps that bound each key); the tiny graphs are also run with every integer tensor
checked (``integer_extremes`` in the test of each model), and the radix grouping and ranked top-k
keys are int32 by construction (tests/models/test_voxelize.py, test_nms.py).
"""
import math

import pytest

from models import zoo
from models.nms import SCORE_LEVELS, index_bits
from models.sparse import out_shape
from models.voxelize import MAX_POINTS

INT32 = 2 ** 31
MARGIN = 2  # empty cells the sparse convs pad each side of a grid with (kernel 3, padding <= 2)


def _grid_bounds(cfg) -> dict[str, int]:
    """Linear indices of the voxel grid and of every sparse level's padded index grid."""
    x0, y0, z0, x1, y1, z1 = cfg.pc_range
    dx, dy, dz = cfg.voxel_size
    shape = (round((z1 - z0) / dz), round((y1 - y0) / dy), round((x1 - x0) / dx))
    out = {"voxel linear index": math.prod(shape)}
    backbone = getattr(cfg, "backbone3d", None)
    for i, spec in enumerate(backbone.stages if backbone else ()):
        out[f"level {i} padded index grid"] = math.prod(n + 2 * MARGIN for n in shape)
        shape = out_shape(shape, 3, spec.stride, spec.padding)
    if hasattr(cfg, "max_voxels") and hasattr(cfg, "max_points"):
        out["voxel slot table"] = cfg.max_voxels * cfg.max_points
    return out


def _selection_bounds(model, cfg) -> dict[str, int]:
    """Every selection's NMS pair index (K * K) and ranking key (score level above index rank)."""
    sites = {f"head {i}": h.cfg.nms_pre for i, h in enumerate(m for m in model.modules()
                                                             if type(m).__name__ == "AnchorHead")}
    for field in ("proposals_train", "proposals_test", "output"):
        if hasattr(cfg, field):
            sites[field] = getattr(cfg, field).nms_pre
    if hasattr(cfg, "pre_nms"):  # PointRCNN: proposals from the top points, final boxes of the RoIs
        sites.update(proposals=cfg.pre_nms, output=cfg.rois)
    out = {}
    for site, k in sites.items():
        out[f"{site} NMS pairs"] = k * k
        out[f"{site} ranking key"] = (SCORE_LEVELS + 1) * 2 ** index_bits(k)
    return out


def _model_bounds(name: str, cfg) -> dict[str, int]:
    """Keys particular to one architecture."""
    if name == "parta2":
        g, k = cfg.roi_grid, cfg.proposals_test.rois
        return {"RoI-aware pooling cells": k * g ** 3, "stacked RoI grid": k * (g + 1) * g * g}
    if name == "pv_rcnn":
        return {"RoI grid points": cfg.proposals_test.rois * cfg.grid ** 3,
                "ball query keys": MAX_POINTS + max(cfg.raw_nsamples + cfg.grid_nsamples)}
    if name == "point_rcnn":
        return {"pooled RoI rows": cfg.rois * cfg.pool_samples}
    if name == "mvx_net":
        h, w = cfg.image_hw
        return {"image pixel index": h * w}
    return {}


@pytest.mark.parametrize("profile", zoo.PROFILES)
@pytest.mark.parametrize("name", zoo.MODEL_NAMES)
def test_integer_keys_fit_int32(name, profile):
    model, cfg = zoo.build(name, profile), zoo.config(name, profile)
    bounds = {**_selection_bounds(model, cfg), **_model_bounds(name, cfg)}
    if hasattr(cfg, "voxel_size"):
        bounds.update(_grid_bounds(cfg))
    assert bounds, "no bound checked"
    over = {k: v for k, v in bounds.items() if v >= INT32}
    assert not over, f"{name}/{profile}: keys beyond int32: {over}"
