"""The GEMM / non-GEMM split of benchmarks/ort_profile.py on a graph whose FLOPs are known."""
import numpy as np
import pytest
from onnx import TensorProto, helper

from benchmarks.ort_profile import gemm_flops, profile_frames


def test_gemm_flops_by_hand():
    assert gemm_flops("Conv", [[1, 8, 10, 12], [16, 8, 3, 3]], [[1, 16, 10, 12]]) == 2 * 16 * 120 * 8 * 9
    assert gemm_flops("ConvTranspose", [[1, 8, 5, 6], [8, 4, 2, 2]], [[1, 4, 10, 12]]) == 2 * 8 * 30 * 4 * 4
    assert gemm_flops("MatMul", [[7, 5], [5, 3]], [[7, 3]]) == 2 * 7 * 3 * 5
    assert gemm_flops("Gemm", [[5, 7], [5, 3]], [[7, 3]]) == 2 * 7 * 3 * 5  # A transposed


def test_profile_counts_gemm_flops_of_a_small_graph(tmp_path):
    rng = np.random.default_rng(0)
    w = helper.make_tensor("w", TensorProto.FLOAT, [16, 8, 3, 3], rng.random(16 * 8 * 9, np.float32))
    m = helper.make_tensor("m", TensorProto.FLOAT, [12, 20], rng.random(240, np.float32))
    nodes = [helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
             helper.make_node("MatMul", ["c", "m"], ["y"]), helper.make_node("Sigmoid", ["y"], ["z"])]
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 8, 10, 12])],
                              [helper.make_tensor_value_info("z", TensorProto.FLOAT, None)], [w, m])
    path = tmp_path / "g.onnx"
    path.write_bytes(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]).SerializeToString())
    x = rng.random((1, 8, 10, 12), np.float32)
    got = profile_frames(path, [{"x": x}, {"x": x}])
    want = 2 * 16 * 120 * 8 * 9 + 2 * (16 * 10 * 20) * 12  # the Conv, then (1, 16, 10, 12) @ (12, 20)
    assert got["gemm_gflop"] == pytest.approx(want / 1e9)
    assert got["gemm_ms"] > 0 and got["other_ms"] >= 0
