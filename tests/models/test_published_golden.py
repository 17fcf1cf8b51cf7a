"""The imported published networks against golden data of the reference implementations
(``benchmarks/golden_published.py``: the references' own modules on CPU, random weights by a
seeded rule in their checkpoint layout, one frame). The checkpoint is rebuilt here from the rule,
imported through ``sotif-bench import``'s code and run: intermediate tensors and the final Car
boxes must match."""
import collections
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.golden_weights import RULES, fill
from harness.import_weights import import_checkpoint
from models import zoo

GOLDEN = Path(__file__).parents[1] / "golden"
CASES = [("openpcdet", "pointpillars"), ("openpcdet", "second")]


def load(source: str, model: str, config: str = "") -> dict:
    """The golden data of a published network (``config``: a named other config of it, e.g. ``car``)."""
    g = dict(np.load(GOLDEN / f"{source}_{model}{'_' + config if config else ''}.npz"))
    assert str(g["rule"]) in RULES
    dims, values = g["shape_dims"], g["shape_values"]
    ends = np.cumsum(dims)
    g["shapes"] = [tuple(int(v) for v in values[e - d:e]) for d, e in zip(dims, ends)]
    return g


def reference_file(g: dict, path: Path) -> None:
    """The golden weights in OpenPCDet's checkpoint format (a legacy non-zip save)."""
    values = fill([str(n) for n in g["names"]], g["shapes"], int(g["seed"]), float(g["cls_bias"]),
                  float(g.get("head_scale", 1.0)), str(g["rule"]))
    state = collections.OrderedDict((n, torch.from_numpy(v)) for n, v in values.items())
    torch.save({"epoch": 0, "it": 0, "model_state": state, "optimizer_state": {}, "version": "pcdet+0.6.0"}, path,
               _use_new_zipfile_serialization=False)


def imported(source: str, model: str, tmp: Path):
    g = load(source, model)
    reference_file(g, tmp / "ref.pth")
    import_checkpoint(tmp / "ref.pth", source, model, tmp / "ours.pt")
    return zoo.load_checkpoint(tmp / "ours.pt")[0], g


def car_boxes(g: dict) -> tuple[np.ndarray, np.ndarray]:
    car = g["labels"] == list(g["classes"]).index("Car")
    return g["boxes"][car], g["scores"][car]


def differences(boxes, scores, want_boxes, want_scores) -> tuple[float, float]:
    """(largest box-value difference (yaw modulo 2 pi), largest score difference) of two equally long
    box lists matched by score, boxes of equal score (to 1e-4) by x: two boxes can tie in score."""
    a = np.lexsort((boxes[:, 0], -np.round(scores, 4)))
    b = np.lexsort((want_boxes[:, 0], -np.round(want_scores, 4)))
    turn = np.remainder(boxes[a][:, 6] - want_boxes[b][:, 6] + math.pi, 2 * math.pi) - math.pi
    box = max(float(np.abs(boxes[a][:, :6] - want_boxes[b][:, :6]).max(initial=0.0)),
              float(np.abs(turn).max(initial=0.0)))
    return box, float(np.abs(scores[a] - want_scores[b]).max(initial=0.0))


def assert_same_boxes(boxes, scores, want_boxes, want_scores):
    """Same count; every box value within 1e-3, scores within 1e-4."""
    assert len(boxes) == len(want_boxes)
    box, score = differences(boxes, scores, want_boxes, want_scores)
    assert box <= 1e-3 and score <= 1e-4, (box, score)


def assert_two_stage(g: dict, proposals, rcnn, final, tol: dict) -> None:
    """A two-stage network against golden data ``g``: ``proposals`` (rois, scores, labels: OpenPCDet keeps the
    RPN's logit as the RoI score, and labels are compared in score order); ``rcnn`` (class logits, refined boxes)
    of the reference's RoIs in its order, within ``tol`` and 1e-3 m / rad; ``final`` (boxes, scores): the Car ones."""
    rois, roi_scores, roi_labels = (np.asarray(t) for t in proposals)
    want_scores = torch.sigmoid(torch.from_numpy(g["roi_scores"])).numpy()
    assert_same_boxes(rois, roi_scores, g["rois"], want_scores)
    order, want_order = np.argsort(-roi_scores, kind="stable"), np.argsort(-want_scores, kind="stable")
    np.testing.assert_array_equal(roi_labels[order], g["roi_labels"][want_order])
    logit, got = (np.asarray(t) for t in rcnn)
    np.testing.assert_allclose(logit, g["rcnn_cls"], **tol)
    want = g["rcnn_boxes"]
    turn = np.remainder(got[:, 6] - want[:, 6] + math.pi, 2 * math.pi) - math.pi
    np.testing.assert_allclose(got[:, :6], want[:, :6], rtol=0, atol=1e-3)
    assert np.abs(turn).max() <= 1e-3
    want_boxes, want_final = car_boxes(g)
    assert len(want_boxes) > 0
    assert_same_boxes(*(np.asarray(t) for t in final), want_boxes, want_final)


def assert_matches_golden(net, g: dict) -> None:
    """``net`` on the golden frame against the reference: sampled BEV map and class logits, final Car boxes."""
    points = torch.from_numpy(g["points"])
    with torch.no_grad():
        bev = net.bev(points)[0]  # (C, H, W) the map entering the 2D backbone
        feats = net.backbone2d(bev[None])  # the rest of forward(points), the map computed once
        cls, _, _ = net.head(feats)  # (A, 3) class logits
        boxes, scores = net.head.detect(feats)
    np.testing.assert_allclose(bev.numpy()[tuple(g["bev_index"].T)], g["bev_value"], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(cls.numpy()[tuple(g["cls_index"].T)], g["cls_value"], rtol=1e-4, atol=1e-4)
    want_boxes, want_scores = car_boxes(g)
    assert len(want_boxes) > 0
    assert_same_boxes(boxes.numpy(), scores.numpy(), want_boxes, want_scores)


@pytest.mark.parametrize("source,model", CASES)
def test_imported_network_is_the_reference(source, model, tmp_path):
    net, g = imported(source, model, tmp_path)
    assert_matches_golden(net, g)


def assert_import_refused(tmp_path, capsys, model: str, config: str, cases) -> None:
    """``import --from openpcdet --model <model>`` of each (name, state dict, expected words) in ``cases``: exit
    2, a message naming OpenPCDet's ``config`` and the words, and no output file."""
    from harness.cli import main
    from tests.harness.test_import_weights import openpcdet_file
    for name, state, want in cases:
        openpcdet_file(tmp_path / f"{name}.pth", state)
        assert main(["import", "--from", "openpcdet", "--model", model, "--checkpoint",
                     str(tmp_path / f"{name}.pth"), "--out", str(tmp_path / "o.pt")]) == 2
        err = capsys.readouterr().err
        assert f"does not hold the network of OpenPCDet tools/cfgs/kitti_models/{config}" in err and want in err, err
        assert not (tmp_path / "o.pt").exists()
