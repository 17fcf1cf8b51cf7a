import dataclasses
import hashlib
import json
import os
import re

import numpy as np
import onnx
import pytest
import torch

from models import graph_cache
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


@dataclasses.dataclass(frozen=True)
class _CachedConfig:
    pc_range: tuple = (0.0, -10.0, -3.0, 20.0, 10.0, 1.0)
    width: int = 8


class _Cached(_Toy):
    """A contract model with a dataclass config (so its traced graph is cached) whose weights the
    optimiser folds: a gain's exponential and a Linear layer's transposed matrix."""

    def __init__(self, cfg: _CachedConfig = _CachedConfig(), seed: int = 0):
        super().__init__()
        self.cfg = cfg
        gen = torch.Generator().manual_seed(seed)
        self.hidden = torch.nn.Linear(4, cfg.width)
        self.gain = torch.nn.Parameter(torch.zeros(cfg.width))
        self.score = torch.nn.Linear(cfg.width, 1)
        with torch.no_grad():
            for tensor in self.parameters():
                tensor.copy_(torch.rand(tensor.shape, generator=gen) - 0.5)
        self.eval()

    def forward(self, points):
        keep = (points[:, 0] >= 0) & (points[:, 0] < 20)
        pts = points[keep]  # (M, 4)
        boxes = torch.cat([pts[:, :3], torch.ones_like(pts[:, :3]), pts[:, 3:4]], dim=1)  # (M, 7)
        hidden = torch.relu(self.hidden(pts) * torch.exp(self.gain))  # (M, width)
        return boxes, torch.sigmoid(self.score(hidden))[:, 0]


def _export_lines(model, path, cache) -> list[str]:
    """Export with ``SOTIF_BENCH_GRAPH_CACHE=cache``; the stage lines it printed."""
    lines = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(graph_cache.ENV, str(cache))
        export_onnx(model, path, {"sotif.profile": "tiny"}, say=lines.append)
    return lines


def test_a_cached_graph_exports_a_new_checkpoint_as_a_fresh_export_does(tmp_path):
    cache = tmp_path / "graphs"
    first = _export_lines(_Cached(seed=1), tmp_path / "a.onnx", cache)
    assert [line.split(" (")[0] for line in first[:-1]] == [
        "export toy: tracing", "export toy: optimising", "export toy: checking", "export toy: writing"]
    assert re.fullmatch(r"export toy: written in \d+ s", first[-1])
    assert len(list(cache.glob("*.graph"))) == 1
    warm = _export_lines(_Cached(seed=2), tmp_path / "b.onnx", cache)
    assert warm[0].startswith("export toy: traced graph from the cache")
    _export_lines(_Cached(seed=2), tmp_path / "fresh.onnx", "off")
    assert (tmp_path / "b.onnx").read_bytes() == (tmp_path / "fresh.onnx").read_bytes()
    assert (tmp_path / "b.onnx").read_bytes() != (tmp_path / "a.onnx").read_bytes()
    points = np.random.default_rng(0).uniform([0, -10, -3, 0], [20, 10, 1, 1], (50, 4)).astype(np.float32)
    with torch.no_grad():
        expected = _Cached(seed=2)(torch.from_numpy(points))[1].numpy()
    np.testing.assert_allclose(run_onnx(tmp_path / "b.onnx", points)[1], expected, rtol=1e-5)
    _export_lines(_Cached(_CachedConfig(width=4)), tmp_path / "c.onnx", cache)  # another config: its own entry
    assert len(list(cache.glob("*.graph"))) == 2


@pytest.mark.parametrize("damage", ["truncate", "garbage", "other_shapes"])
def test_a_damaged_or_foreign_cache_entry_is_ignored_and_rebuilt(tmp_path, damage):
    cache = tmp_path / "graphs"
    _export_lines(_Cached(seed=1), tmp_path / "a.onnx", cache)
    [entry] = cache.glob("*.graph")
    good = entry.read_bytes()
    if damage == "truncate":
        entry.write_bytes(good[: len(good) // 2])
    elif damage == "garbage":
        entry.write_bytes(b"0" * 64 + b"\n" + b"\x08\x99")
    else:  # a well-formed entry whose weights have other shapes than the model's (same key)
        other = onnx.ModelProto.FromString(good.partition(b"\n")[2])
        weight = next(i for i in other.graph.initializer if i.name in graph_cache.weights(_Cached()))
        weight.dims[0] += 1
        payload = other.SerializeToString()
        entry.write_bytes(hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload)
    lines = _export_lines(_Cached(seed=2), tmp_path / "b.onnx", cache)
    assert lines[0].startswith("export toy: tracing")
    assert entry.read_bytes() == good  # rebuilt
    _export_lines(_Cached(seed=2), tmp_path / "fresh.onnx", "off")
    assert (tmp_path / "b.onnx").read_bytes() == (tmp_path / "fresh.onnx").read_bytes()


def test_weights_that_do_not_map_one_to_one_are_never_cached(tmp_path, monkeypatch):
    """Where filling the model's own weights into the emptied graph does not give back the traced
    graph byte for byte, no entry is written and every export traces."""
    monkeypatch.setattr(graph_cache, "_raw", lambda tensor: b"")
    cache = tmp_path / "graphs"
    _export_lines(_Cached(seed=1), tmp_path / "a.onnx", cache)
    assert not list(cache.glob("*.graph"))
    assert _export_lines(_Cached(seed=1), tmp_path / "b.onnx", cache)[0].startswith("export toy: tracing")


def test_cache_folder_and_key(tmp_path, monkeypatch):
    monkeypatch.delenv(graph_cache.ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert graph_cache.cache_dir() == tmp_path / "sotif-bench" / "graphs"
    monkeypatch.setenv(graph_cache.ENV, "off")
    assert graph_cache.cache_dir() is None
    monkeypatch.setenv(graph_cache.ENV, str(tmp_path / "g"))
    assert graph_cache.cache_dir() == tmp_path / "g"
    key = graph_cache.cache_key(_Cached(), 18)
    assert key == graph_cache.cache_key(_Cached(seed=3), 18)  # weights are not in the key
    assert key != graph_cache.cache_key(_Cached(_CachedConfig(width=4)), 18)
    assert key != graph_cache.cache_key(_Cached(), 19)
    assert graph_cache.cache_key(_Toy(), 18) is None  # a config that is not a dataclass: not cached


def cached_export_equals_fresh(tmp_path, name: str) -> None:
    """Tiny profiles: the graph cached from one model's export, filled with another model's weights
    (BatchNorm statistics moved as by training), gives the bytes of that model's fresh export. The
    entry is the suite's (tests/conftest.py): when another test exported the model first (its own
    weights, not these), its trace is the one filled; else model 0's export writes it. PV-RCNN's and
    MVX-Net's run in their own modules, after those modules' exports (one more trace each: the fresh one)."""
    from models import zoo
    from models.export import OPSET

    def model(seed):
        torch.manual_seed(seed)
        net = zoo.build(name, "tiny").eval()
        with torch.no_grad():
            for buf in net.buffers():
                if buf.is_floating_point():
                    buf.uniform_(0.5, 1.5)
        return net

    cache, first = graph_cache.cache_dir(), model(0)
    if graph_cache.load(graph_cache.cache_key(first, OPSET), first) is None:
        _export_lines(first, tmp_path / "a.onnx", cache)
    assert "from the cache" in _export_lines(model(1), tmp_path / "warm.onnx", cache)[0]
    _export_lines(model(1), tmp_path / "fresh.onnx", "off")
    assert (tmp_path / "warm.onnx").read_bytes() == (tmp_path / "fresh.onnx").read_bytes()


def test_cached_export_of_a_model_equals_its_fresh_export(tmp_path):
    cached_export_equals_fresh(tmp_path, "pointpillars")


def test_a_batchnorm_momentum_does_not_key_the_graph_but_its_other_settings_do():
    """reset_norm_statistics sets every BatchNorm's momentum to None (train-mode averaging only, not in the
    traced graph): the model keeps its entry; an eps, which is in the graph, keys another."""
    from models import zoo
    from models.base import reset_norm_statistics
    from models.export import OPSET

    model = zoo.build("pointpillars", "tiny")
    key = graph_cache.cache_key(model, OPSET)
    reset_norm_statistics(model)
    assert graph_cache.cache_key(model, OPSET) == key
    next(m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)).eps = 0.01
    assert graph_cache.cache_key(model, OPSET) != key


def test_models_of_one_class_and_config_whose_parts_differ_never_share_a_graph_entry():
    import dataclasses as dc

    from models.graph_cache import cache_key

    @dc.dataclass(frozen=True)
    class Part:
        post: str

    class Inner(torch.nn.Module):
        def __init__(self, post):
            super().__init__()
            self.setting = Part(post)
            self.lin = torch.nn.Linear(2, 2)

    class Outer(torch.nn.Module):
        def __init__(self, post):
            super().__init__()
            self.cfg = Part("same")
            self.inner = Inner(post)

    a, b = cache_key(Outer("openpcdet"), 18), cache_key(Outer("mmdet3d"), 18)
    assert a and b and a != b and cache_key(Outer("openpcdet"), 18) == a


def test_graph_code_keys_on_code_not_on_comments_docstrings_or_where_a_harness_name_lives(tmp_path):
    source = '''"""A module."""
from harness.types import Sample  # the floor's
from models.base import Detector


def f(x):
    """Add one."""
    return x + 1
'''
    (tmp_path / "a.py").write_text(source)
    key = graph_cache.graph_code(tmp_path)
    same = (source.replace("harness.types", "harness.core.types").replace("Add one.", "One more.")
            .replace("  # the floor's", "").replace("return x + 1", "return (x\n            + 1)  # layout"))
    (tmp_path / "a.py").write_text(same)
    assert graph_cache.graph_code(tmp_path) == key
    for changed in (source.replace("x + 1", "x + 2"), source.replace("models.base", "models.other"),
                    source.replace("import Sample", "import Labels")):
        (tmp_path / "a.py").write_text(changed)
        assert graph_cache.graph_code(tmp_path) != key, changed


def test_the_optimiser_runs_without_the_skipped_rewrite_rules_and_they_change_nothing(tmp_path):
    """onnxscript's SlicesSplit (quadratic in the graph's size) is left out while the optimiser runs, and
    put back after; it names a rule onnxscript has (else the skip would do nothing unnoticed); a graph
    optimised without it is the one optimised with it, byte for byte (all seven graphs, tiny and compact:
    benchmarks/export_optimiser.py)."""
    import onnxscript.rewriter as rewriter

    from benchmarks.export_optimiser import compare
    from models.export import SKIPPED_REWRITE_RULES, without_rewrite_rules

    names = [rule.name for rule in rewriter._DEFAULT_REWRITE_RULES]
    assert set(SKIPPED_REWRITE_RULES) <= set(names)
    with without_rewrite_rules(SKIPPED_REWRITE_RULES):
        assert [rule.name for rule in rewriter._DEFAULT_REWRITE_RULES] == [
            n for n in names if n not in SKIPPED_REWRITE_RULES]
    assert [rule.name for rule in rewriter._DEFAULT_REWRITE_RULES] == names
    assert compare("pointpillars", "tiny")["same bytes"]
