import json
import numpy as np
import pytest

from harness.core import kitti
from harness.infer import ContractError, OnnxDetector, check_contract, predict


def test_contract_accepts_conforming_file_and_counts_ops(make_onnx, tmp_path):
    info = check_contract(make_onnx(tmp_path / "c.onnx"))
    assert info.architecture == "centroid" and not info.two_stage and not info.uses_camera
    assert info.op_histogram == {"Concat": 1, "Identity": 1, "ReduceMean": 1, "Slice": 1}
    assert check_contract(make_onnx(tmp_path / "t.onnx", two_stage=True)).two_stage


@pytest.mark.parametrize("kwargs, message", [
    ({"drop_output": "scores"}, "no output named 'scores'"),
    ({"metadata": {}}, "sotif.contract"),
    ({"custom_op": True}, "non-standard op my.ops::Voxelize"),
])
def test_contract_refuses_broken_files(make_onnx, tmp_path, kwargs, message):
    path = make_onnx(tmp_path / "bad.onnx", **kwargs)
    with pytest.raises(ContractError, match=rf"bad\.onnx: .*{message}"):
        check_contract(path)


def _opset_17(model):
    model.opset_import[0].version = 17


def _custom_op_in_a_branch(model):
    from onnx import TensorProto, helper
    branch = lambda op, domain: helper.make_graph(  # noqa: E731
        [helper.make_node(op, ["points"], ["y"], domain=domain)], "branch", [],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 4])])
    model.graph.node.append(helper.make_node("If", ["cond"], ["unused"], then_branch=branch("Secret", "my.ops"),
                                             else_branch=branch("Identity", "")))
    model.graph.initializer.append(helper.make_tensor("cond", TensorProto.BOOL, [], [True]))
    model.opset_import.append(helper.make_opsetid("my.ops", 1))


def _external_constant(model):
    from onnx import TensorProto, helper
    value = helper.make_tensor("c", TensorProto.FLOAT, [1], [1.0])
    value.ClearField("float_data")
    value.data_location = TensorProto.EXTERNAL
    value.external_data.add(key="location", value="c.bin")
    model.graph.node.append(helper.make_node("Constant", [], ["unused"], value=value))


def _without(key):
    def drop(model):
        keep = [p for p in model.metadata_props if p.key != key]
        del model.metadata_props[:]
        model.metadata_props.extend(keep)
    return drop


def _metadata(key, value):
    def set_(model):
        next(p for p in model.metadata_props if p.key == key).value = value
    return set_


@pytest.mark.parametrize("mutate, message", [
    (_opset_17, "opset 17 of the default domain; the contract needs opset >= 18"),
    (_custom_op_in_a_branch, "non-standard op my.ops::Secret"),
    (_external_constant, "tensor 'c' is stored in an external file"),
    (_without("sotif.point_cloud_range"), "metadata_props lack sotif.point_cloud_range"),
    (_metadata("sotif.point_cloud_range", "banana"), "'sotif.point_cloud_range' must be six numbers"),
    (_metadata("sotif.point_cloud_range", "0,-40,-3,70.4,40"), "'sotif.point_cloud_range' must be six numbers"),
    (_metadata("sotif.classes", "Pedestrian"), "'sotif.classes' must be \"Car\" .*got 'Pedestrian'"),
    (_metadata("sotif.classes", "Car,Cyclist"), "'sotif.classes' must be \"Car\""),
    (_metadata("sotif.architecture", " "), "'sotif.architecture' is empty"),
])
def test_contract_refuses_rules_broken_deeper_in_the_file(make_onnx, tmp_path, mutate, message):
    """Rules a file can break beyond its top-level nodes and first metadata key."""
    import onnx
    path = make_onnx(tmp_path / "deep.onnx")
    model = onnx.load(str(path))
    mutate(model)
    onnx.save(model, str(path))
    with pytest.raises(ContractError, match=rf"deep\.onnx: .*{message}"):
        check_contract(path)


def test_a_foreign_file_needs_no_provenance_keys_and_may_give_its_range_comma_separated(make_onnx, tmp_path, dataset):
    from harness.infer import point_cloud_range
    meta = {"sotif.contract": "1", "sotif.architecture": "theirs", "sotif.classes": "Car",
            "sotif.point_cloud_range": "0,-40,-3,70.4,40,1"}
    info = check_contract(make_onnx(tmp_path / "theirs.onnx", metadata=meta))
    assert info.provenance == {} and info.architecture == "theirs"
    assert predict(info.path, dataset, tmp_path / "pred", progress=False)["provenance"] == {}
    ours = check_contract(make_onnx(tmp_path / "ours.onnx", metadata={**meta, "sotif.data_hash": "d1",
                                                                      "sotif.config_hash": ""}))
    assert ours.provenance == {"data_hash": "d1"}  # shown when present, an empty value is absent
    expected = [0.0, -40.0, -3.0, 70.4, 40.0, 1.0]
    for text in ("0,-40,-3,70.4,40,1", " 0, -40, -3, 70.4, 40, 1 ", "[0, -40, -3, 70.4, 40, 1]"):
        assert point_cloud_range(text) == expected
    for text in ("", "[0, -40, -3, 70.4, 40]", "70.4,-40,-3,0,40,1", "0,-40,-3,nan,40,1", "[0,-40,-3,70.4,40,", "{}",
                 "0;-40;-3;70.4;40;1"):
        assert point_cloud_range(text) is None, text


def test_detector_refuses_boxes_and_scores_of_different_counts(make_onnx, tmp_path):
    import onnx
    path = make_onnx(tmp_path / "m.onnx")
    model = onnx.load(str(path))
    score = next(t for t in model.graph.initializer if t.name == "score_c")
    score.CopyFrom(onnx.helper.make_tensor("score_c", onnx.TensorProto.FLOAT, [2], [0.9, 0.8]))
    onnx.save(model, str(path))
    with pytest.raises(ValueError, match=r"m\.onnx: outputs 'boxes' \[1, 7\] and 'scores' \[2\]"):
        OnnxDetector(path)(np.ones((10, 4), np.float32))


def test_contract_refuses_garbage_and_missing(tmp_path):
    (tmp_path / "junk.onnx").write_bytes(b"\x00\x01 not a model")
    with pytest.raises(ContractError, match=r"junk\.onnx"):
        check_contract(tmp_path / "junk.onnx")
    with pytest.raises(ContractError, match="file not found"):
        check_contract(tmp_path / "none.onnx")
    (tmp_path / "empty.onnx").write_bytes(b"")
    with pytest.raises(ContractError, match=r"empty\.onnx: empty: no ONNX model in it"):
        check_contract(tmp_path / "empty.onnx")
    with pytest.raises(ContractError, match="is a folder, not an ONNX file"):
        check_contract(tmp_path)


def test_detector_runs_and_rejects_nan_outputs(make_onnx, tmp_path):
    det = OnnxDetector(make_onnx(tmp_path / "c.onnx"))
    pts = np.random.default_rng(0).normal(size=(100, 4)).astype(np.float32)
    out = det(pts)
    np.testing.assert_allclose(out["boxes"][0, :3], pts[:, :3].mean(axis=0), rtol=1e-5, atol=1e-6)
    pts[3, 0] = np.nan
    with pytest.raises(ValueError, match="output 'boxes' contains NaN"):
        det(pts)  # a NaN box is refused, never written as a result


def test_detector_refuses_a_box_of_size_zero_or_less(make_onnx, tmp_path):
    import onnx
    from onnx import numpy_helper
    model = onnx.load(str(make_onnx(tmp_path / "c.onnx")))
    dims = next(t for t in model.graph.initializer if t.name == "dims")
    dims.CopyFrom(numpy_helper.from_array(np.array([[4.0, -1.8, 1.5, 0.0]], np.float32), "dims"))
    onnx.save(model, str(tmp_path / "neg.onnx"))
    pts = np.random.default_rng(0).normal(size=(100, 4)).astype(np.float32)
    with pytest.raises(ValueError, match=r"neg\.onnx: output 'boxes' has a box with a size <= 0 \(box 0: l w h 4 -1\.8 1\.5\)"):
        OnnxDetector(tmp_path / "neg.onnx")(pts)


def test_predict_writes_kitti_results_and_resumes(make_onnx, tmp_path, dataset):
    onnx_path = make_onnx(tmp_path / "c.onnx", two_stage=True)
    out = tmp_path / "pred"
    summary = predict(onnx_path, dataset, out, progress=False)
    assert summary["n_frames"] == 6 and summary["n_timed"] == 6 and summary["latency_ms_p50"] > 0
    res = kitti.read_labels(out / "000000.txt", with_score=True)
    assert len(res) == 1 and res.score[0] == pytest.approx(0.9)
    calib = kitti.read_calib(kitti.frame_path(dataset, "calib", "000000"))
    pts = kitti.read_points(kitti.frame_path(dataset, "velodyne", "000000"))
    np.testing.assert_allclose(res.to_lidar(calib)[0, :3], pts[:, :3].mean(axis=0), atol=2e-3)
    assert (out / "rois" / "000000.txt").is_file()
    first = (out / "latency_ms.csv").read_text().splitlines()
    assert first[0] == "frame_id,latency_ms" and [r.split(",")[0] for r in first[1:]] == [f"{i:06d}" for i in range(6)]
    (out / "000003.txt").unlink()
    with open(out / ".frames.jsonl", "a") as f:
        f.write('{"frame_id": "000004", "laten')  # a record cut off by a kill
    again = predict(onnx_path, dataset, out, progress=False)
    # only the missing frame ran; the summary covers the earlier session's frames too
    assert again["n_timed"] == 6 and again == json.loads((out / "predict.json").read_text())
    rows = (out / "latency_ms.csv").read_text().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == [f"{i:06d}" for i in range(6)]
    assert [r for r in rows if not r.startswith("000003")] == [r for r in first if not r.startswith("000003")]
    assert [r for r in rows if r.startswith("000003")] != [r for r in first if r.startswith("000003")]  # timed again


def test_predict_names_the_frame_a_model_fails_on_and_keeps_the_frames_before(make_onnx, tmp_path, dataset,
                                                                              monkeypatch):
    scan = kitti.read_points(kitti.frame_path(dataset, "velodyne", "000002"))
    call = OnnxDetector.__call__

    def nan_on_frame_2(self, points, *args):  # the model's output check failing on that frame's scan
        if np.array_equal(points, scan):
            raise ValueError(f"{self.info.path}: output 'boxes' contains NaN or inf")
        return call(self, points, *args)

    monkeypatch.setattr(OnnxDetector, "__call__", nan_on_frame_2)
    out = tmp_path / "pred"
    with pytest.raises(ValueError, match=r"c\.onnx: output 'boxes' contains NaN or inf \(frame 000002: .*000002\.bin\)"):
        predict(make_onnx(tmp_path / "c.onnx"), dataset, out, progress=False)
    assert sorted(f.name for f in out.glob("*.txt")) == ["000000.txt", "000001.txt"]


def test_predict_refuses_a_frame_image_that_is_no_image_or_not_the_calibrated_one(make_onnx, tmp_path, dataset):
    """A LiDAR-only model reads the image's size only (the camera view results are kept in): a file
    that is no image, or an image the calibration cannot belong to, is an error naming it, never a
    frame of silently dropped boxes."""
    image = kitti.frame_path(dataset, "image_2", "000002")
    image.write_text("not an image")
    onnx_path = make_onnx(tmp_path / "c.onnx")
    with pytest.raises(ValueError, match=r"000002\.png: not a readable image"):
        predict(onnx_path, dataset, tmp_path / "a", progress=False)
    kitti.write_image(image, np.zeros((20, 50, 3), np.uint8))
    with pytest.raises(ValueError, match=r"000002\.png: the image is 50 x 20 pixels, but .*000002\.txt's P2"):
        predict(onnx_path, dataset, tmp_path / "b", progress=False)
    assert sorted(f.name for f in (tmp_path / "b").glob("*.txt")) == ["000000.txt", "000001.txt"]


def test_predict_refuses_a_split_of_no_frames(make_onnx, tmp_path, dataset):
    (dataset / "ImageSets" / "none.txt").write_text("\n")
    with pytest.raises(ValueError, match=r"none\.txt: lists no frames: nothing to predict"):
        predict(make_onnx(tmp_path / "c.onnx"), dataset, tmp_path / "pred", split="none", progress=False)
    assert not (tmp_path / "pred").exists()


def test_predict_into_a_folder_of_other_results(make_onnx, tmp_path, dataset):
    """Results of another data set are replaced, never reused; result files no earlier predict
    recorded are refused and left alone; files of other names stay."""
    from tests.harness.conftest import make_dataset
    onnx_path = make_onnx(tmp_path / "c.onnx", two_stage=True)
    out = tmp_path / "pred"
    predict(onnx_path, dataset, out, progress=False)
    (out / "notes.md").write_text("mine")
    other = make_dataset(tmp_path / "other", seed=9)
    summary = predict(onnx_path, other, out, progress=False)
    assert summary["n_timed"] == 6  # every frame again
    calib = kitti.read_calib(kitti.frame_path(other, "calib", "000000"))
    pts = kitti.read_points(kitti.frame_path(other, "velodyne", "000000"))
    res = kitti.read_labels(out / "000000.txt", with_score=True)
    np.testing.assert_allclose(res.to_lidar(calib)[0, :3], pts[:, :3].mean(axis=0), atol=2e-3)
    assert (out / "notes.md").read_text() == "mine"
    from harness.core.files import folder_lock
    with folder_lock(out, "predict"):  # another predict is writing there
        with pytest.raises(ValueError, match=r"pred: another sotif-bench predict is writing to this folder"):
            predict(onnx_path, dataset, out, progress=False)

    (out / "000999.txt").write_text("Car 0 0 0 1 1 2 2 1.5 1.6 4 0 1.6 20 0 0.99\n")  # not predict's
    with pytest.raises(ValueError, match=r"pred: holds result files \(000999\.txt, \.\.\.\) that the earlier "):
        # a new request (the split as a file): the earlier results would go, this one is no result of theirs
        predict(onnx_path, dataset, out, split=dataset / "ImageSets" / "test.txt", progress=False)
    assert (out / "000999.txt").is_file() and (out / "000000.txt").is_file()

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "000001.txt").write_text("Car 0 0 0 0 0 10 10 1.5 1.6 3.9 0 1.6 20 0 0.5\n")
    with pytest.raises(ValueError, match=r"foreign: holds result files \(000001\.txt"):
        predict(onnx_path, dataset, foreign, progress=False)
    assert sorted(p.name for p in foreign.iterdir()) == ["000001.txt"]
    summary = tmp_path / "summary"
    summary.mkdir()
    (summary / "predict.json").write_text("my own notes")
    with pytest.raises(ValueError, match=r"summary: holds result files \(predict\.json"):
        predict(onnx_path, dataset, summary, progress=False)
    assert (summary / "predict.json").read_text() == "my own notes"


def test_openvino_runtime_agrees_with_onnxruntime(make_onnx, tmp_path):
    pytest.importorskip("openvino")
    path = make_onnx(tmp_path / "c.onnx", two_stage=True)
    pts = np.random.default_rng(1).normal(size=(300, 4)).astype(np.float32)
    a, b = OnnxDetector(path)(pts), OnnxDetector(path, runtime="openvino")(pts)
    assert list(a) == list(b) == ["boxes", "scores", "rois", "roi_scores"]
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-5, atol=1e-6)
