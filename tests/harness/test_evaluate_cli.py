import json
import shutil

import numpy as np
import pytest

from harness import kitti
from harness.cli import main
from harness.evaluate import evaluate, recall_at_iou


def copy_as_predictions(dataset, out, score=0.8):
    out.mkdir(parents=True)
    for p in (dataset / "training" / "label_2").glob("*.txt"):
        lab = kitti.read_labels(p)
        lab.score = np.full(len(lab), score)
        kitti.write_labels(out / p.name, lab)
    return out


def test_perfect_predictions_and_groups(tmp_path, dataset):
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    res = evaluate(dataset, pred, group_by="weather", meta=dataset / "meta" / "frames.csv", n_bootstrap=20)
    assert res["n_frames"] == 6 and res["n_car"] == 18
    # 18 cars < 41 sample points: KITTI's sampling caps AP at (18 - 1) / 40
    assert res["headline"]["3d"]["0.7"] == pytest.approx(17 / 40 * 100)
    assert res["recall"]["rcnn"] == {"0.3": 1.0, "0.5": 1.0, "0.7": 1.0}
    rows = res["groups"]["rows"]
    assert set(rows) == {"ClearNoon", "HardRainNight"} and rows["ClearNoon"]["n_frames"] == 3
    lo, hi = rows["ClearNoon"]["headline_ci95"]["3d"]
    assert lo <= rows["ClearNoon"]["headline"]["3d"]["0.7"] + 1e-9 and hi >= lo


def test_recall_at_iou_brute_force():
    calib = kitti.kitti_calib()
    gt_boxes = np.array([[20, 0, -0.9, 4, 1.8, 1.5, 0], [30, 3, -0.9, 4, 1.8, 1.5, 0]], np.float32)
    gt = kitti.Labels.from_lidar(gt_boxes, calib, ["Car", "Car"])
    shifted = gt_boxes.copy()
    shifted[0, 0] += 1.0  # IoU (4 - 1) / (4 + 1) = 0.6
    pred = kitti.Labels.from_lidar(shifted[:1], calib, ["Car"], score=[1.0])
    assert recall_at_iou([gt], [pred]) == pytest.approx({"0.3": 0.5, "0.5": 0.5, "0.7": 0.0})


def test_cli_evaluate_writes_json_and_exit_codes(tmp_path, dataset, capsys):
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    out = tmp_path / "results.json"
    code = main(["evaluate", "--labels", str(dataset / "training" / "label_2"), "--predictions", str(pred),
                 "--split", str(dataset / "ImageSets" / "test.txt"), "--group-by", "weather",
                 "--meta", str(dataset / "meta" / "frames.csv"), "--output", str(out)])
    assert code == 0
    res = json.loads(out.read_text())
    assert set(res["kitti"]) == {"bbox", "bev", "3d", "aos"}
    assert set(res["kitti"]["3d"]) == {"0.7", "0.5", "official_0.5"}
    assert set(res["kitti"]["3d"]["0.7"]["R40"]) == {"easy", "moderate", "hard"}
    assert "headline 3D AP40" not in capsys.readouterr().err
    gt_as_results = main(["evaluate", "--labels", str(dataset), "--predictions", str(dataset / "training" / "label_2"),
                          "--output", str(tmp_path / "self.json")])
    assert gt_as_results == 0  # result lines without a score count with score 0, as in the reference
    assert json.loads((tmp_path / "self.json").read_text())["recall"]["rcnn"]["0.7"] == 1.0
    (pred / "000002.txt").write_text("Car 0 0 0 1 2 3\n")
    before = out.read_text()
    assert main(["evaluate", "--labels", str(dataset), "--predictions", str(pred), "--output", str(out)]) == 2
    err = capsys.readouterr().err
    assert "000002.txt:1" in err and "expected 15 fields" in err
    assert out.read_text() == before  # a failed run leaves earlier results alone
    shutil.rmtree(pred)
    assert main(["evaluate", "--labels", str(dataset), "--predictions", str(pred), "--output", str(out)]) == 2
    assert main(["evaluate", "--labels", str(dataset), "--predictions", str(tmp_path), "--group-by", "nope",
                 "--meta", str(dataset / "meta" / "frames.csv"), "--output", str(out)]) == 2


def test_cli_evaluate_refuses_bad_paths_and_tables_before_work(tmp_path, dataset, capsys):
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    args = ["evaluate", "--quiet", "--labels", str(dataset), "--predictions", str(pred)]  # --quiet after the command
    (tmp_path / "a_file").write_text("mine")
    for output, message in ((tmp_path, "is a folder; expected a file path"),
                            (tmp_path / "a_file" / "r.json", "a_file: is a file")):
        assert main(args + ["--output", str(output)]) == 2
        assert message in capsys.readouterr().err
    assert (tmp_path / "a_file").read_text() == "mine"
    with pytest.raises(SystemExit):
        main(args + ["--output", str(tmp_path / "r.json"), "--bootstrap", "0"])
    meta = (dataset / "meta" / "frames.csv").read_text().splitlines()
    (tmp_path / "empty_cell.csv").write_text("\n".join([meta[0], meta[1].replace("ClearNoon", ""), *meta[2:]]) + "\n")
    (tmp_path / "short_ids.csv").write_text("\n".join([meta[0]] + [str(int(m[:6])) + m[6:] for m in meta[1:]]) + "\n")
    grouped = args + ["--output", str(tmp_path / "r.json"), "--group-by", "weather", "--meta"]
    assert main(grouped + [str(tmp_path / "empty_cell.csv")]) == 2
    assert "empty_cell.csv: column 'weather' is empty for 1 frames of the split (first: 000000)" in capsys.readouterr().err
    assert main(grouped + [str(tmp_path / "short_ids.csv")]) == 0  # ids padded to six digits match


def test_cli_evaluate_bring_your_own_onnx(make_onnx, tmp_path, dataset):
    onnx_path = make_onnx(tmp_path / "mine.onnx")
    out = tmp_path / "byo" / "results.json"
    assert main(["--quiet", "evaluate", "--onnx", str(onnx_path), "--data", str(dataset), "--output", str(out)]) == 0
    assert json.loads(out.read_text())["n_frames"] == 6
    bad = make_onnx(tmp_path / "bad.onnx", metadata={})
    assert main(["--quiet", "predict", "--onnx", str(bad), "--data", str(dataset), "--out", str(tmp_path / "p")]) == 2
