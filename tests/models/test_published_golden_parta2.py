"""The imported Part-A2 against golden data of OpenPCDet's own modules (``benchmarks/golden_parta2.py``:
PartA2.yaml's network on CPU, random weights by the seeded rule in its checkpoint layout, one frame on
one thread, CPU stand-ins for its RoI-aware pooling and rotated NMS). The checkpoint is rebuilt here
from the rule, imported through ``sotif-bench import``'s code and run: the bird's-eye map, the RPN
class logits, the voxels' segmentation and part scores, the 100 proposals, the RCNN outputs of the
reference's proposals and the final Car boxes must match."""
import collections

import numpy as np
import torch

from models.roi_head import decode_canonical, finalize, propose, roi_support
from tests.harness import published_layouts as layouts
from tests.models.test_published_golden import assert_import_refused, assert_two_stage, imported, load

TOL = dict(rtol=1e-4, atol=1e-4)


def by_centre(xyz: torch.Tensor, want_xyz: np.ndarray) -> np.ndarray:
    """(S,) rows of our voxel centres xyz (V, 3) at the reference's voxel centres (S, 3)."""
    dist = torch.cdist(torch.from_numpy(want_xyz).double(), xyz.double())  # (S, V) m
    near, rows = dist.min(dim=1)
    assert float(near.max()) < 1e-4
    return rows.numpy()


def test_imported_parta2_is_openpcdet(tmp_path):
    net, g = imported("openpcdet", "parta2", tmp_path)
    points = torch.from_numpy(g["points"])
    with torch.no_grad():
        xyz, feats, seg, part, bev = net.voxel_stage(points)
        feats2d = net.backbone2d(bev)
        cls = net.rpn(feats2d)[0]  # (A, 3) class logits
        rois, roi_scores, roi_labels = propose(net.rpn, feats2d, net.cfg.proposals_test)
        want_rois = torch.from_numpy(g["rois"])
        logit, deltas = net.rcnn(want_rois, xyz, feats, torch.sigmoid(seg), torch.sigmoid(part))
        rcnn_boxes = decode_canonical(deltas, want_rois, net.cfg.output.max_log_size)
        # the rest of PartA2.second_stage, on our proposals
        ours = net.rcnn(rois, xyz, feats, torch.sigmoid(seg), torch.sigmoid(part))
        boxes, scores, _ = finalize(rois, roi_scores, *ours, net.cfg.output, roi_support(xyz, rois), roi_labels,
                                    net.reported)
    assert xyz.shape[0] == int(g["num_voxels"])
    np.testing.assert_allclose(bev[0].numpy()[tuple(g["bev_index"].T)], g["bev_value"], **TOL)
    np.testing.assert_allclose(cls.numpy()[tuple(g["cls_index"].T)], g["cls_value"], **TOL)
    rows = by_centre(xyz, g["seg_xyz"])
    np.testing.assert_allclose(torch.sigmoid(seg).numpy()[rows], g["seg_value"], **TOL)
    rows = by_centre(xyz, g["part_xyz"])
    np.testing.assert_allclose(torch.sigmoid(part).numpy()[rows, g["part_index"][:, 1]], g["part_value"], **TOL)
    # the proposals; the RCNN on the reference's proposals; the final Car boxes
    assert_two_stage(g, (rois, roi_scores, roi_labels), (logit, rcnn_boxes), (boxes, scores), TOL)


def test_another_network_exits_2_naming_the_mismatch(tmp_path, capsys):
    """SECOND's file, and Part-A2's with a per-class point head (CLASS_AGNOSTIC False), are refused."""
    g = load("openpcdet", "parta2")
    second = collections.OrderedDict((n, torch.zeros(s)) for n, s in layouts.openpcdet_second(True).items())
    shapes = dict(zip((str(n) for n in g["names"]), g["shapes"]))
    per_class = collections.OrderedDict((n, torch.zeros(s)) for n, s in shapes.items())
    per_class["point_head.cls_layers.0.weight"] = torch.zeros(3, 16)
    per_class["point_head.cls_layers.0.bias"] = torch.zeros(3)
    cases = (("second", second, "tensors of ours no reference tensor fills (170): part_head.0.bias"),
             ("per_class", per_class, "point_head.cls_layers.0.weight (3, 16) for seg_head.0.weight (1, 16)"))
    assert_import_refused(tmp_path, capsys, "parta2", "PartA2.yaml", cases)
