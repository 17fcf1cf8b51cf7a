"""PointPillars tiny: output shapes (loss and ONNX agreement: test_single_stage.py)."""
import numpy as np
import torch

from harness.dataset import synthetic_sample
from models import zoo

NAME = "pointpillars"


def _model(seed=0):
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return zoo.build(NAME, "tiny")


def test_output_shapes_and_pillars():
    model = _model().eval()
    sample = synthetic_sample(np.random.default_rng(0))
    pseudo = model.bev(torch.from_numpy(sample.points))
    _, h, w = model.grid.shape
    assert pseudo.shape == (1, model.cfg.pfn_channels, h, w)
    boxes, scores = model(torch.from_numpy(sample.points))
    assert boxes.shape[1] == 7 and scores.shape == (boxes.shape[0],)
    assert model.head.anchors.shape == (h // 2 * (w // 2) * 2, 7)
