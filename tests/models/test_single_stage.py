"""The one-stage detectors (PointPillars, SECOND, DV-SECOND), tiny profile: the loss falls on a
tiny scene and onnxruntime == torch on random clouds of several sizes, an empty one included.
Model-specific shape checks live in test_<name>.py."""
import numpy as np
import pytest
import torch

from harness.dataset import synthetic_sample
from models import zoo
from models.base import reset_norm_statistics
from models.export import example_inputs, export_checkpoint, integer_extremes, run_onnx

NAMES = ("pointpillars", "second", "dv_second")


def _model(name, seed=0):
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return zoo.build(name, "tiny")


@pytest.mark.parametrize("name", NAMES)
def test_loss_falls_on_tiny_scene(name):
    model = _model(name)
    sample = synthetic_sample(np.random.default_rng(1))
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(12):
        loss = model.loss([sample])["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert np.mean(losses[-3:]) < 0.6 * np.mean(losses[:3])


def _calibrate_norms(model):
    """BatchNorm running statistics = averages over a few random clouds (train-mode passes)."""
    reset_norm_statistics(model)  # cumulative average of the passes below
    model.train()
    with torch.no_grad():
        for seed in range(3):
            model.backbone2d(model.bev(example_inputs(model, 3000, seed=100 + seed)[0]))
    model.eval()


@pytest.fixture(scope="module", params=NAMES)
def exported(request, tmp_path_factory):
    """A checkpoint of a random tiny model, exported to ONNX through export_checkpoint.

    BatchNorm statistics are calibrated on random clouds and the class layer gets large random
    weights and a bias that puts every anchor of an empty cloud at logit <= -3, like a trained
    head: cells that see no points stay below the threshold, cells near points get scores
    spread over (0, 1). (A fresh model
    scores every anchor ~0.01, where float noise alone reorders near-ties.)"""
    name = request.param
    model = _model(name, 3)
    _calibrate_norms(model)
    gen = torch.Generator().manual_seed(4)
    cls = model.head.conv_cls
    with torch.no_grad():
        cls.weight.copy_(torch.randn(cls.weight.shape, generator=gen) * 3 / cls.weight.shape[1] ** 0.5)
        empty = model.head(model.backbone2d(model.bev(torch.zeros(0, 4))))[0]  # (A,) logits
        cls.bias -= empty.reshape(-1, cls.bias.shape[0]).max(dim=0).values + 3.0
        model.head.conv_box.weight.copy_(torch.randn(model.head.conv_box.weight.shape, generator=gen) * 0.1)
    tmp = tmp_path_factory.mktemp(name)
    torch.save({"model": name, "profile": "tiny", "state_dict": model.state_dict(), "epoch": 0}, tmp / "c.pt")
    path = export_checkpoint(tmp / "c.pt", tmp / f"{name}.onnx", expected_model=name)
    reference, _ = zoo.load_checkpoint(tmp / "c.pt")
    return path, reference


@pytest.mark.parametrize("n", [0, 1, 700, 4000])
def test_onnxruntime_equals_torch(exported, n):
    path, model = exported
    points = example_inputs(model, n, seed=n)[0]
    with torch.no_grad():
        boxes, scores = model(points)
    got_boxes, got_scores = run_onnx(path, points.numpy())
    assert got_boxes.shape == tuple(boxes.shape) and got_scores.shape == tuple(scores.shape)
    if n > 100:
        assert boxes.shape[0] > 0  # boxes reach the outputs through threshold and NMS
    np.testing.assert_allclose(got_scores, scores.numpy(), atol=1e-4)
    np.testing.assert_allclose(_rows(got_boxes), _rows(boxes.numpy()), atol=1e-3, rtol=1e-4)


def test_integer_intermediates_fit_int32(exported):
    """OpenVINO computes int64 in int32: no integer tensor of the graph may leave that range."""
    path, model = exported
    assert max(integer_extremes(path, example_inputs(model, 4000, seed=1)[0].numpy()).values()) < 2 ** 31


def _rows(boxes):
    """Boxes in lexicographic order: equal scores may come out in either order."""
    return boxes[np.lexsort(np.round(boxes, 2).T[::-1])]


def test_van_and_truck_are_ignored_not_background():
    """The Car targets: Car boxes are the positives; Van, Truck and DontCare boxes are regions ignored (neither
    car nor background); any other class is background."""
    from harness.core.types import Sample
    from models.single_stage import frame_targets
    boxes = np.array([[10.0 * (i + 1), 0, -0.9, 4.5, 1.9, 1.5, 0.0] for i in range(5)], np.float32)
    sample = Sample("000000", np.zeros((3, 4), np.float32), boxes,
                    np.array(["Car", "Van", "Truck", "DontCare", "Pedestrian"]))
    points, cars, ignore = frame_targets(sample, "cpu")
    assert points.shape == (3, 4)
    assert cars[:, 0].tolist() == [10.0]
    assert ignore[:, 0].tolist() == [20.0, 30.0, 40.0]
