"""OpenVINO next to onnxruntime: latency and agreement, and failures reported as findings."""
import sys

import numpy as np
import pytest

from harness.runtime import compare_openvino, outputs_agree


def test_outputs_agree_sorts_by_score_and_spots_differences():
    rng = np.random.default_rng(0)
    boxes, scores = rng.normal(size=(5, 7)).astype(np.float32), rng.random(5).astype(np.float32)
    perm = rng.permutation(5)
    assert outputs_agree({"boxes": boxes, "scores": scores}, {"boxes": boxes[perm], "scores": scores[perm]}) == (True, 0.0, 0.0)
    moved = boxes.copy()
    moved[2, 0] += 2e-4  # beyond 1e-4 absolute: a float32 box at 50 m resolves ~4e-6
    ok, score_diff, box_diff = outputs_agree({"boxes": boxes, "scores": scores}, {"boxes": moved, "scores": scores})
    assert not ok and score_diff == 0.0 and box_diff == pytest.approx(2e-4, rel=1e-3)
    moved[2, 0] = boxes[2, 0] + 5e-5
    assert outputs_agree({"boxes": boxes, "scores": scores}, {"boxes": moved, "scores": scores})[0]
    assert not outputs_agree({"boxes": boxes, "scores": scores}, {"boxes": boxes[:4], "scores": scores[:4]})[0]


def test_openvino_matches_onnxruntime_on_the_data(make_onnx, dataset, tmp_path):
    pytest.importorskip("openvino")
    res = compare_openvino(make_onnx(tmp_path / "c.onnx", two_stage=True), dataset, n_frames=3)
    assert res["error"] is None
    agreement = res["agreement"]
    assert agreement["same_boxes"] == 1.0 and agreement["frames"] == 3 and agreement["box_atol"] == 1e-4
    assert agreement["max_abs_box_diff"] <= 1e-4
    assert res["latency_ms_p50"] > 0 and res["latency_ms_p90"] >= res["latency_ms_p50"]


def test_openvino_missing_or_failing_is_reported(make_onnx, dataset, tmp_path, monkeypatch):
    path = make_onnx(tmp_path / "c.onnx")
    monkeypatch.setitem(sys.modules, "openvino", None)  # import fails as when the extra is absent
    assert compare_openvino(path, dataset) == {"error": "not installed"}
    monkeypatch.undo()
    ov = pytest.importorskip("openvino")

    def refuse(self, *a, **k):
        raise RuntimeError("Exception from src/core.cpp:132:\nunsupported operation Foo\nmore detail\n")
    monkeypatch.setattr(ov.Core, "compile_model", refuse)
    assert compare_openvino(path, dataset)["error"] == "compile: RuntimeError: unsupported operation Foo more detail"


def test_openvino_is_compiled_in_f32(make_onnx, tmp_path, monkeypatch):
    """On AVX-512 BF16 CPUs OpenVINO's default precision is bf16: the runner asks for f32."""
    from harness.infer import OnnxDetector
    ov = pytest.importorskip("openvino")
    seen = []
    original = ov.Core.compile_model

    def spy(self, model, device, config=None):
        seen.append(config)
        return original(self, model, device, config or {})
    monkeypatch.setattr(ov.Core, "compile_model", spy)
    OnnxDetector(make_onnx(tmp_path / "c.onnx"), runtime="openvino")
    assert seen and seen[0].get("INFERENCE_PRECISION_HINT") == "f32"
