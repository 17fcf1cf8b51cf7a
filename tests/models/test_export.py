import json
import os

import numpy as np
import onnx
import pytest
import torch

from models.base import Detector
from models.export import ExportError, export_onnx, op_histogram, run_onnx


class _Config:
    pc_range = (0.0, -10.0, -3.0, 20.0, 10.0, 1.0)


class _Toy(Detector):
    """A minimal contract model: one 'box' per in-range point, scored by a linear layer."""

    architecture = "toy"

    def __init__(self):
        super().__init__()
        self.cfg = _Config()
        self.score = torch.nn.Linear(4, 1)

    def forward(self, points):
        keep = (points[:, 0] >= 0) & (points[:, 0] < 20)
        pts = points[keep]  # (M, 4)
        boxes = torch.cat([pts[:, :3], torch.ones_like(pts[:, :3]), pts[:, 3:4]], dim=1)  # (M, 7)
        return boxes, torch.sigmoid(self.score(pts))[:, 0]


class _Camera(_Toy):
    uses_camera = True


def test_export_writes_contract_metadata_and_matches_torch(tmp_path):
    torch.manual_seed(0)
    model = _Toy()
    hist = export_onnx(model, tmp_path / "toy.onnx", {"sotif.profile": "tiny", "sotif.data_hash": "abc"})
    proto = onnx.load(str(tmp_path / "toy.onnx"))
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["sotif.contract"] == "1" and meta["sotif.architecture"] == "toy"
    assert meta["sotif.classes"] == "Car" and meta["sotif.profile"] == "tiny"
    assert json.loads(meta["sotif.point_cloud_range"]) == list(_Config.pc_range)
    assert meta["sotif.two_stage"] == "false" and meta["sotif.uses_camera"] == "false"
    assert meta["sotif.data_hash"] == "abc" and meta["sotif.config_hash"] == ""
    assert json.loads(meta["sotif.op_histogram"]) == hist == op_histogram(proto)
    assert proto.opset_import[0].version >= 18
    assert [i.name for i in proto.graph.input] == ["points"]
    assert [o.name for o in proto.graph.output] == ["boxes", "scores"]
    assert not list(tmp_path.glob(".*tmp"))  # atomic write left no temp file
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "toy.onnx").stat().st_mode & 0o777 == 0o666 & ~umask  # readable as any written file
    rng = np.random.default_rng(0)
    for n in (0, 5, 300):
        pts = (rng.random((n, 4)) * [30, 20, 4, 1] - [5, 10, 3, 0]).astype(np.float32)
        with torch.no_grad():
            boxes, scores = model(torch.from_numpy(pts))
        got = run_onnx(tmp_path / "toy.onnx", pts)
        np.testing.assert_allclose(got[0], boxes.numpy(), rtol=1e-6)
        np.testing.assert_allclose(got[1], scores.numpy(), atol=1e-6)


def test_histogram_counts_subgraph_ops():
    inner = onnx.helper.make_graph([onnx.helper.make_node("Relu", ["x"], ["y"]),
                                    onnx.helper.make_node("Relu", ["y"], ["z"])], "body", [], [])
    outer = onnx.helper.make_graph([onnx.helper.make_node("Loop", ["m", "c"], ["o"], body=inner),
                                    onnx.helper.make_node("Relu", ["a"], ["b"])], "main", [], [])
    assert op_histogram(onnx.helper.make_model(outer)) == {"Loop": 1, "Relu": 3}


def test_camera_model_without_image_size_is_refused(tmp_path):
    with pytest.raises(ExportError, match="image_hw"):
        export_onnx(_Camera(), tmp_path / "cam.onnx", {})
    assert not (tmp_path / "cam.onnx").exists()


class _Loop(_Toy):
    """A contract model with an ONNX Loop (farthest point sampling), whose traced body the exporter
    names by a per-process call counter."""

    def forward(self, points):
        from models.pointnet2 import farthest_point_sample
        pts = points[farthest_point_sample(points[:, :3], 8)]  # (M, 4)
        boxes = torch.cat([pts[:, :3], torch.ones_like(pts[:, :3]), pts[:, 3:4]], dim=1)
        return boxes, torch.sigmoid(self.score(pts))[:, 0]


def test_export_is_byte_reproducible(tmp_path):
    torch.manual_seed(0)
    model = _Loop()
    export_onnx(model, tmp_path / "a.onnx", {})
    export_onnx(model, tmp_path / "b.onnx", {})
    assert (tmp_path / "a.onnx").read_bytes() == (tmp_path / "b.onnx").read_bytes()
    proto = onnx.load(str(tmp_path / "a.onnx"))
    assert "Loop" in op_histogram(proto)
    assert not any(node.metadata_props for node in proto.graph.node)  # no stack traces, no paths


def test_reset_norm_statistics_averages_the_passes_that_follow():
    from models.base import reset_norm_statistics
    bn = torch.nn.BatchNorm1d(3)
    bn.train()
    bn(torch.randn(8, 3) * 5 + 2)  # statistics of an earlier pass, with the default momentum
    reset_norm_statistics(torch.nn.Sequential(bn))
    batches = [torch.randn(16, 3) * s + m for s, m in ((1.0, 0.0), (2.0, 3.0))]
    for x in batches:
        bn(x)
    np.testing.assert_allclose(bn.running_mean.numpy(), np.mean([x.mean(0).numpy() for x in batches], 0), rtol=1e-5)
    assert bn.momentum is None and int(bn.num_batches_tracked) == 2
