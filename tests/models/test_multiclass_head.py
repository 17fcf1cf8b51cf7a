import dataclasses

import numpy as np
import torch

from harness.core.boxes import iou_bev
from models.multiclass_head import (MMDET3D_DIR_OFFSET, PublishedHeadConfig, axis_positions, mmdet3d_select,
                                    openpcdet_select, published_anchors)
from models.pointpillars import CONFIGS as PP
from models.second import CONFIGS as SECOND
from models.vfe import PillarVFE
from models.voxel_backbone import output_shape
from models.voxelize import Grid, hard_voxelize

RANGE = (0.0, -8.0, -3.0, 16.0, 8.0, 1.0)


def test_anchors_at_corners_and_centres():
    cfg = PublishedHeadConfig()
    a = published_anchors(RANGE, (4, 6), cfg).reshape(4, 6, 3, 2, 7).numpy()
    np.testing.assert_allclose(a[2, 5, 1, 1], [16.0, -8 + 2 * 16 / 3, -0.6 + 1.73 / 2, 0.8, 0.6, 1.73, 1.57], rtol=1e-6)
    np.testing.assert_allclose(a[0, 3, 0, 0, :3], [3 * 16 / 5, -8.0, -1.0], rtol=1e-6)
    centred = published_anchors(RANGE, (4, 6), dataclasses.replace(cfg, anchor_grid="centres")).reshape(4, 6, 3, 2, 7)
    np.testing.assert_allclose(centred[1, 2, 2, 0, :2].numpy(), [2.5 * 16 / 6, -8 + 1.5 * 4], rtol=1e-6)


def test_mmdet3d_anchors_spread_over_the_range_ends_included():
    """Anchor3DRangeGenerator: linspace(lo, hi, n) (KITTI: 176 anchors 70.4 / 175 m apart, not at the 0.4 m
    cells' centres); OpenPCDet's arange gives the same positions but for float32 rounding."""
    xs = axis_positions(0.0, 70.4, 176, "linspace")
    assert xs[0] == 0.0 and xs[-1] == np.float32(70.4)
    np.testing.assert_allclose(np.diff(xs.numpy()), 70.4 / 175, atol=1e-5)  # float32 steps near 70 m
    np.testing.assert_allclose(xs.numpy(), axis_positions(0.0, 70.4, 176, "arange").numpy(), atol=1e-5)
    np.testing.assert_allclose(axis_positions(-40.0, 40.0, 200, "centres")[[0, -1]].numpy(), [-39.8, 39.8], rtol=1e-6)


def _greedy(boxes, scores, thresh):
    """Brute force: greedy NMS over the exact rotated BEV IoU, boxes given best first."""
    keep = []
    for i in range(len(boxes)):
        if all(iou_bev(boxes[j:j + 1], boxes[i:i + 1])[0, 0] <= thresh for j in keep):
            keep.append(i)
    return np.array(keep, dtype=np.int64)


def _random(n, seed):
    g = np.random.default_rng(seed)
    boxes = np.c_[g.uniform(0, 12, (n, 2)), g.uniform(-1, 0, n), g.uniform(0.5, 4, (n, 3)), g.uniform(-3, 3, n)]
    return boxes.astype(np.float32), g.uniform(0, 1, (n, 3)).astype(np.float32)


def test_openpcdet_selection_matches_brute_force():
    cfg = PublishedHeadConfig(nms_pre=60, nms_iou=0.01, max_out=12, score_thresh=0.3)
    boxes, scores = _random(200, 1)
    got = openpcdet_select(torch.from_numpy(boxes), torch.from_numpy(scores), cfg)
    best, label = scores.max(1), scores.argmax(1)
    order = np.argsort(-best, kind="stable")[:60]
    order = order[best[order] >= 0.3]
    keep = order[_greedy(boxes[order], best[order], 0.01)][:12]
    np.testing.assert_allclose(got[0].numpy(), boxes[keep])
    np.testing.assert_allclose(got[1].numpy(), best[keep])
    np.testing.assert_array_equal(got[2].numpy(), label[keep])


def test_mmdet3d_selection_matches_brute_force():
    cfg = PublishedHeadConfig(nms_pre=80, nms_iou=0.01, max_out=10, score_thresh=0.5, post="mmdet3d",
                              dir_offset=MMDET3D_DIR_OFFSET)
    boxes, scores = _random(200, 2)
    got = mmdet3d_select(torch.from_numpy(boxes), torch.from_numpy(scores), cfg)
    top = np.argsort(-scores.max(1), kind="stable")[:80]
    rows = []
    for c in range(3):
        order = top[np.argsort(-scores[top, c], kind="stable")]
        order = order[scores[order, c] > 0.5]
        rows += [(scores[i, c], c, i) for i in order[_greedy(boxes[order], scores[order, c], 0.01)]]
    rows = sorted(rows, key=lambda r: -r[0])[:10]
    np.testing.assert_allclose(got[1].numpy(), [r[0] for r in rows])
    np.testing.assert_array_equal(got[2].numpy(), [r[1] for r in rows])
    np.testing.assert_allclose(got[0].numpy(), boxes[[r[2] for r in rows]])


def test_padded_slots_enter_the_pillar_max_as_openpcdet():
    torch.manual_seed(0)
    grid = Grid(RANGE, (2.0, 2.0, 4.0))
    points = torch.rand(300, 4) * torch.tensor([16, 16, 4, 1.0]) + torch.tensor([0, -8, -3, 0.0])
    vfe = PillarVFE(grid, 8, padded_slots=True).eval()
    vfe.norm.running_mean.normal_()
    vfe.norm.bias.data.normal_()
    voxels = hard_voxelize(points, grid, 4, 100)
    with torch.no_grad():
        got = vfe(voxels)
        dec = vfe.decorate(voxels)  # (P, 10)
        padded = torch.zeros(voxels.num_voxels, 4, 10)  # OpenPCDet's (V, T, 10), empty slots zero
        padded[voxels.point2voxel, voxels.slot] = dec
        want = torch.relu(vfe.norm(vfe.linear(padded.reshape(-1, 10)))).reshape(-1, 4, 8).amax(1)
    torch.testing.assert_close(got, want)


def test_published_backbone_input_is_41_deep():
    cfg = SECOND["kitti"].backbone3d
    assert cfg.input_shape((40, 1600, 1408)) == (41, 1600, 1408)
    assert output_shape((40, 1600, 1408), cfg) == (2, 200, 176)  # VoxelBackBone8x: [41 -> 21 -> 11 -> 5 -> 2]


def test_tiny_and_compact_configs_have_no_new_fields():
    for cfgs in (PP, SECOND):
        for profile in ("tiny", "compact"):
            fields = dataclasses.asdict(cfgs[profile])
            assert "padded_slots" not in fields and "classes" not in fields["head"]
            assert "depth_pad" not in fields.get("backbone3d", {})


class _HeadOnly(torch.nn.Module):
    """points -> a BEV map scaled by their mean intensity -> the published head's Car boxes."""

    architecture, two_stage, uses_camera = "head_only", False, False
    input_names, output_names = ("points",), ("boxes", "scores")

    def __init__(self, cfg: PublishedHeadConfig):
        super().__init__()
        from models.multiclass_head import MultiClassAnchorHead
        self.cfg = dataclasses.replace(PP["tiny"], pc_range=RANGE)
        torch.manual_seed(4)
        self.base = torch.nn.Parameter(torch.randn(1, 8, 8, 12))
        self.head = MultiClassAnchorHead(8, (8, 12), RANGE, cfg)
        torch.nn.init.normal_(self.head.conv_cls.bias, 0.0, 1.0)
        torch.nn.init.normal_(self.head.conv_box.weight, 0.0, 0.1)

    def forward(self, points):
        return self.head.detect(self.base * (1 + points[:, 3].mean()))


def test_both_post_processings_export_and_match_torch(tmp_path):
    from models.export import export_onnx, run_onnx
    points = torch.rand(50, 4)
    for cfg in (PublishedHeadConfig(nms_pre=100, max_out=20),
                PublishedHeadConfig(nms_pre=60, max_out=15, post="mmdet3d", anchor_grid="linspace",
                                    dir_offset=MMDET3D_DIR_OFFSET)):
        model = _HeadOnly(cfg).eval()
        export_onnx(model, tmp_path / f"{cfg.post}.onnx", {})
        with torch.no_grad():
            want = model(points)
        got = run_onnx(tmp_path / f"{cfg.post}.onnx", points.numpy())
        assert len(want[0]) > 0 and got[0].shape == tuple(want[0].shape)
        np.testing.assert_allclose(got[0], want[0].numpy(), atol=1e-4)
        np.testing.assert_allclose(got[1], want[1].numpy(), atol=1e-5)
