"""The imported PV-RCNN against golden data of OpenPCDet's own modules (``benchmarks/golden_pvrcnn.py``:
pv_rcnn.yaml's network on CPU, random weights by the seeded rule in its checkpoint layout, one frame on one
thread, CPU stand-ins for its farthest point sampling, ball query, grouping and rotated NMS). The checkpoint
is rebuilt here from the rule, imported through ``sotif-bench import``'s code and run: the bird's-eye map,
the RPN class logits, the keypoints, the keypoint features before and after the fusion and their weights,
the 100 proposals, the RCNN outputs of each proposal and the final Car boxes must match."""
import collections
import math

import numpy as np
import torch

from models.pv_rcnn_published import in_range_points
from models.roi_head import finalize, propose
from tests.models.test_published_golden import assert_import_refused, assert_two_stage, imported, load

TOL = dict(rtol=1e-4, atol=1e-4)


def matching(rois: np.ndarray, want: np.ndarray) -> np.ndarray:
    """(K,) the row of ``rois`` (K, 7) nearest each row of ``want`` (K, 7) (yaw modulo 2 pi), asserting each
    is within 1e-4 and no row is taken twice."""
    diff = np.abs(rois[None] - want[:, None])  # (K, K, 7)
    diff[..., 6] = np.abs(np.remainder(diff[..., 6] + math.pi, 2 * math.pi) - math.pi)
    worst = diff.max(-1)  # (K, K)
    rows = worst.argmin(1)
    assert worst[np.arange(len(want)), rows].max() <= 1e-4 and len(set(rows)) == len(rows)
    return rows


def captured(module: torch.nn.Module, store: dict, key: str):
    """A forward hook keeping the module's first input under ``key`` and its output under ``key + '_out'``."""
    def hook(_, inputs, output):
        store[key], store[key + "_out"] = inputs[0], output
    return module.register_forward_hook(hook)


def test_imported_pv_rcnn_is_openpcdet(tmp_path):
    net, g = imported("openpcdet", "pv_rcnn", tmp_path)
    points = torch.from_numpy(g["points"])
    seen = {}
    hooks = [captured(net.backbone2d, seen, "bev"), captured(net.vsa.fuse, seen, "before"),
             captured(net.vsa.weight, seen, "logit")]
    with torch.no_grad():
        keypoints, kp_feats, _, feats2d, _ = net.stage1(points)
        cls = net.rpn(feats2d)[0]  # (A, 3) class logits
        rois, roi_scores, roi_labels = propose(net.rpn, feats2d, net.cfg.proposals_test)
        logit, deltas = net.stage2(rois, keypoints, kp_feats)  # the rest of PVRCNN.forward
        boxes, scores, rcnn_boxes = finalize(rois, roi_scores, logit, deltas, net.cfg.output, None, roi_labels,
                                             net.reported)
    for h in hooks:
        h.remove()
    want_keypoints = in_range_points(points, net.cfg.pc_range)[torch.from_numpy(g["keypoint_index"]).long(), :3]
    assert torch.equal(keypoints, want_keypoints)  # the same FPS picks, bit for bit
    np.testing.assert_allclose(seen["bev"][0].numpy()[tuple(g["bev_index"].T)], g["bev_value"], **TOL)
    np.testing.assert_allclose(cls.numpy()[tuple(g["cls_index"].T)], g["cls_value"], **TOL)
    np.testing.assert_allclose(seen["before"].numpy()[tuple(g["before_index"].T)], g["before_value"], **TOL)
    np.testing.assert_allclose(seen["before_out"].numpy()[tuple(g["fused_index"].T)], g["fused_value"], **TOL)
    np.testing.assert_allclose(torch.sigmoid(seen["logit_out"][:, 0]).numpy(), g["weights"], **TOL)
    # the proposals; the RCNN of each proposal, ours in the reference's RoI order; the final Car boxes
    rows = matching(rois.numpy(), g["rois"])
    assert_two_stage(g, (rois, roi_scores, roi_labels), (logit[rows], rcnn_boxes[rows]), (boxes, scores), TOL)


def test_another_network_exits_2_naming_the_mismatch(tmp_path, capsys):
    """Part-A2's file, and PV-RCNN's with a per-class keypoint head (CLASS_AGNOSTIC False), are refused."""
    g = load("openpcdet", "pv_rcnn")
    parta2 = load("openpcdet", "parta2")
    other = collections.OrderedDict((str(n), torch.zeros(s)) for n, s in zip(parta2["names"], parta2["shapes"]))
    per_class = collections.OrderedDict((str(n), torch.zeros(s)) for n, s in zip(g["names"], g["shapes"]))
    per_class["point_head.cls_layers.6.weight"] = torch.zeros(3, 256)
    per_class["point_head.cls_layers.6.bias"] = torch.zeros(3)
    cases = (("parta2", other, "tensors of ours no reference tensor fills"),
             ("per_class", per_class, "point_head.cls_layers.6.weight (3, 256) for vsa.weight.6.weight (1, 256)"))
    assert_import_refused(tmp_path, capsys, "pv_rcnn", "pv_rcnn.yaml", cases)
