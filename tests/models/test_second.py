"""SECOND tiny: output shapes (loss and ONNX agreement: test_single_stage.py)."""
import numpy as np
import torch

from harness.dataset import synthetic_sample
from models import zoo

NAME = "second"


def _model(seed=0):
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return zoo.build(NAME, "tiny")


def test_output_shapes_and_voxels():
    model = _model().eval()
    sample = synthetic_sample(np.random.default_rng(0))
    points = torch.from_numpy(sample.points)
    voxels = model.voxelize(points)
    per_voxel = torch.bincount(voxels.point2voxel, minlength=voxels.num_voxels)
    assert int(per_voxel.max()) <= model.cfg.max_points and voxels.num_voxels <= model.cfg.max_voxels
    bev = model.bev(points)
    assert bev.shape == (1, model.cfg.backbone3d.out_channels * 1, 10, 10)  # z collapsed, stride 4
    boxes, scores = model(points)
    assert boxes.shape[1] == 7 and scores.shape == (boxes.shape[0],)
    assert model.head.anchors.shape == (20 * 20 * 2, 7)
