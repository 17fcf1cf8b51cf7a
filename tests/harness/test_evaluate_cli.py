import json
import os
import re
import shutil

import numpy as np
import pytest

from harness.cli import main
from harness.core import kitti
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
    assert res["n_gt"]["all"] == 18 and sum(res["n_gt"][b] for b in ("0-30", "30-50", "50-80")) <= 18
    for b in ("0-30", "30-50", "50-80"):  # perfect detections: the cap (n - 1) / 40 itself
        assert res["distance"]["3d"]["0.7"][b] == pytest.approx(max(res["n_gt"][b] - 1, 0) / 40 * 100)
    assert res["recall"]["rcnn"] == {"0.3": 1.0, "0.5": 1.0, "0.7": 1.0}
    rows = res["groups"]["rows"]
    assert set(rows) == {"ClearNoon", "HardRainNight"} and rows["ClearNoon"]["n_frames"] == 3
    assert 0 <= rows["ClearNoon"]["n_gt_kitti_moderate"] <= rows["ClearNoon"]["n_gt"]["all"] == 9
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
    # without --meta: the labels' own data set's table, else a clear error
    assert main(args + ["--output", str(tmp_path / "r2.json"), "--group-by", "weather"]) == 0
    assert json.loads((tmp_path / "r2.json").read_text())["groups"].keys() == \
        json.loads((tmp_path / "r.json").read_text())["groups"].keys()
    bare = tmp_path / "bare"
    shutil.copytree(dataset / "training", bare / "training")
    assert main(["evaluate", "--quiet", "--labels", str(bare), "--predictions", str(pred), "--group-by", "weather",
                 "--output", str(tmp_path / "r3.json")]) == 2
    assert "--group-by needs --meta meta/frames.csv" in capsys.readouterr().err


def test_cli_evaluate_bring_your_own_onnx(make_onnx, tmp_path, dataset):
    onnx_path = make_onnx(tmp_path / "mine.onnx")
    out = tmp_path / "byo" / "results.json"
    assert main(["--quiet", "evaluate", "--onnx", str(onnx_path), "--data", str(dataset), "--output", str(out)]) == 0
    assert json.loads(out.read_text())["n_frames"] == 6
    bad = make_onnx(tmp_path / "bad.onnx", metadata={})
    assert main(["--quiet", "predict", "--onnx", str(bad), "--data", str(dataset), "--out", str(tmp_path / "p")]) == 2


def _random_frames(root, frames: int, seed: int) -> list[str]:
    """Label and result folders of cars at random headings and distances: Vans, Pedestrians,
    DontCare regions with false positives inside, occlusion, truncation, noisy detections (some
    turned by pi, some named Van) and pure false positives."""
    rng = np.random.default_rng(seed)
    calib = kitti.kitti_calib()
    ids = []
    for f in range(frames):
        fid = f"{f:06d}"
        ids.append(fid)
        k = int(rng.integers(0, 7))
        boxes = np.c_[rng.uniform(5, 60, k), rng.uniform(-15, 15, k), rng.uniform(-1.0, -0.7, k),
                      rng.uniform(3.5, 4.8, k), rng.uniform(1.6, 2.0, k), rng.uniform(1.3, 1.8, k),
                      rng.uniform(-np.pi, np.pi, k)]
        names = rng.choice(["Car"] * 6 + ["Van", "Pedestrian", "DontCare"], k)
        gt = kitti.Labels.from_lidar(boxes, calib, list(names), truncated=rng.choice([0, 0, 0.1, 0.2, 0.4], k),
                                     occluded=rng.choice([0, 0, 1, 2, 3], k))
        lines = [line for line, name in zip(kitti.format_labels(gt).splitlines(), names) if name != "DontCare"]
        for b in gt.bbox[names == "DontCare"]:
            lines.append(f"DontCare -1 -1 -10 {b[0] - 20:.2f} {b[1] - 20:.2f} {b[2] + 20:.2f} {b[3] + 20:.2f} "
                         "-1 -1 -1 -1000 -1000 -1000 -10")
        (root / "gt").mkdir(parents=True, exist_ok=True)
        (root / "gt" / f"{fid}.txt").write_text("".join(line + "\n" for line in lines))
        seen = rng.random(k) < 0.8
        noisy = boxes[seen] + np.c_[rng.normal(0, 0.15, (seen.sum(), 2)), rng.normal(0, 0.05, seen.sum()),
                                    boxes[seen, 3:6] * rng.uniform(-0.06, 0.06, (seen.sum(), 3)),
                                    rng.normal(0, 0.1, seen.sum()) + np.pi * (rng.random(seen.sum()) < 0.1)]
        det_names = np.where(rng.random(seen.sum()) < 0.85, names[seen], rng.choice(["Car", "Van"], seen.sum()))
        det_names = np.where(det_names == "DontCare", "Car", det_names)  # a car found inside a DontCare region
        m = int(rng.integers(0, 4))
        fps = np.c_[rng.uniform(5, 75, m), rng.uniform(-15, 15, m), np.full(m, -0.85), np.tile([4.0, 1.8, 1.5], (m, 1)),
                    rng.uniform(-3, 3, m)]
        dt = kitti.Labels.from_lidar(np.r_[noisy, fps], calib, [*det_names, *rng.choice(["Car", "Car", "Van"], m)],
                                     score=rng.random(len(noisy) + m))
        kitti.write_labels(root / "dt" / f"{fid}.txt", dt)
    return ids


def _flat(d, prefix=""):
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


@pytest.mark.parametrize("seed", [1, 2])
def test_evaluate_equals_an_independent_port_of_the_reference(tmp_path, seed):
    """Every kitti.*, headline.* and distance.* number on 40 random frames (random headings)
    equals the loop-per-object port of kitti_object_eval_python in tests/harness/kitti_reference.py."""
    from tests.harness.kitti_reference import evaluate_folders
    ids = _random_frames(tmp_path, 40, seed)
    ours = _flat(evaluate(tmp_path / "gt", tmp_path / "dt", n_bootstrap=1))
    reference = evaluate_folders(tmp_path / "gt", tmp_path / "dt", ids)
    assert len(reference) == 64
    assert all(0 < reference[f"kitti.{m}.0.7.R40.moderate"] < 100 for m in ("bbox", "bev", "3d", "aos"))
    for key, value in reference.items():
        assert ours[key] == pytest.approx(value, abs=1e-9), key


def test_cli_exit_status_of_disk_and_internal_errors(monkeypatch, tmp_path, capsys):
    """A full or read-only disk is bad input (2, naming the path); another OSError is internal (1)."""
    import errno
    import harness.cli as cli
    for code, expected in ((errno.ENOSPC, 2), (errno.EROFS, 2), (errno.EIO, 1)):
        def fail(a, code=code):
            raise OSError(code, os.strerror(code), str(tmp_path / "results.json"))
        monkeypatch.setattr(cli, "cmd_evaluate", fail)  # the parser binds it when main builds it
        assert cli.main(["evaluate", "--output", str(tmp_path / "results.json")]) == expected
        err = capsys.readouterr().err
        assert "results.json" in err


def test_evaluate_refuses_nonsense_labels_and_notes_swapped_folders(tmp_path, dataset, capsys):
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    labels = tmp_path / "labels"
    shutil.copytree(dataset / "training" / "label_2", labels)
    args = ["--quiet", "evaluate", "--bootstrap", "2", "--output", str(tmp_path / "r.json")]
    lines = (labels / "000001.txt").read_text().splitlines()
    kitti_dontcare = "DontCare -1 -1 -10 500.0 180.0 520.0 190.0 -1 -1 -1 -1000 -1000 -1000 -10"
    (labels / "000001.txt").write_text("\n".join([kitti_dontcare, ""] + lines) + "\n")  # line 3 is lines[0]
    assert main(args + ["--labels", str(labels), "--predictions", str(pred)]) == 0  # KITTI's DontCare rows pass
    for field, value, message in ((8, "-1.5", "box sizes (h w l) must be > 0, got -1.5"),
                                  (1, "1.20", "truncation must be in [0, 1], got 1.2"),
                                  (2, "-1", "occlusion must be 0, 1, 2 or 3, got -1")):
        bad = lines[0].split()
        bad[field] = value
        (labels / "000001.txt").write_text("\n".join([kitti_dontcare, "", " ".join(bad)] + lines[1:]) + "\n")
        assert main(args + ["--labels", str(labels), "--predictions", str(pred)]) == 2
        assert f"{labels / '000001.txt'}:3: {message}" in capsys.readouterr().err
    # the folders swapped: the result files given as labels are refused, labels given as results get a note
    assert main(args + ["--labels", str(pred), "--predictions", str(dataset / "training" / "label_2")]) == 2
    assert f"{pred / '000000.txt'}:1: has a score (16th field), as a prediction file does" in capsys.readouterr().err
    assert main(args + ["--labels", str(dataset), "--predictions", str(dataset / "training" / "label_2")]) == 0
    assert "is it a label folder (--labels and --predictions swapped)?" in capsys.readouterr().err
    assert main(args + ["--labels", str(dataset), "--predictions", str(pred)]) == 0
    assert "swapped" not in capsys.readouterr().err


def test_a_result_box_with_a_size_of_zero_or_less_is_refused_naming_its_line(tmp_path, dataset):
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    path = pred / "000002.txt"
    lines = path.read_text().splitlines()
    fields = lines[1].split()
    fields[8] = "-1.5"  # h
    path.write_text("\n".join([lines[0], " ".join(fields), *lines[2:]]) + "\n")
    with pytest.raises(kitti.KittiError, match=r"000002\.txt:2: box sizes \(h w l\) must be > 0, got -1\.5 "):
        evaluate(dataset, pred)


@pytest.mark.parametrize("folder", ["labels", "predictions"])
def test_an_inverted_2d_box_is_refused_naming_its_line(tmp_path, dataset, folder):
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    labels = tmp_path / "labels"
    shutil.copytree(dataset / "training" / "label_2", labels)
    path = (labels if folder == "labels" else pred) / "000001.txt"
    lines = path.read_text().splitlines()
    fields = lines[0].split()
    fields[5], fields[7] = fields[7], fields[5]  # y1 <-> y2
    assert float(fields[5]) > float(fields[7])
    path.write_text("\n".join([" ".join(fields), *lines[1:]]) + "\n")
    with pytest.raises(kitti.KittiError, match=r"000001\.txt:1: the 2D box \(x1 y1 x2 y2\) must have x1 <= x2 and "
                                               r"y1 <= y2"):
        evaluate(labels, pred)


@pytest.mark.parametrize("column", ["frame_id", "sky"])
def test_group_by_a_column_that_names_no_condition_is_refused(tmp_path, dataset, column):
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    with pytest.raises(kitti.KittiError, match=rf"frames\.csv: --group-by '{column}': no such condition column "
                                               r"\(columns: split, weather\)"):
        evaluate(dataset, pred, group_by=column, meta=dataset / "meta" / "frames.csv")


def test_labels_as_predictions_on_five_cars_print_the_count_and_the_cap(tmp_path, capsys):
    from tests.harness.conftest import make_dataset
    data = make_dataset(tmp_path / "data", n_frames=3, cars=2, seed=4)
    for i, p in enumerate(sorted((data / "training" / "label_2").glob("*.txt"))):
        lab = kitti.read_labels(p).select(np.arange(2 if i < 2 else 1))  # 2 + 2 + 1 = 5 cars
        lab.truncated[:] = 0.2  # above easy's 0.15: no easy car
        kitti.write_labels(p, lab)
    pred = copy_as_predictions(data, tmp_path / "pred")
    assert main(["evaluate", "--labels", str(data), "--predictions", str(pred), "--output", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["n_car"] == res["n_gt"]["all"] == 5 and res["headline"]["3d"]["0.7"] == pytest.approx(10.0)
    assert "(all distances, no height filter, 5 cars): 3D@0.7 10.00 (<= 10.00)" in out
    assert "over n <= 40 cars AP40 is at most (n - 1) / 40" in out
    counts = res["n_gt_kitti"]
    assert counts["easy"] == 0 and re.search(r"cars counted +0 +{moderate} +{hard}\n".format(**counts), out)
    for d, n in counts.items():
        assert (f"no {d} cars" in out) == (n == 0)
    for b, n in res["n_gt"].items():
        if b != "all":
            assert (f"{b} m no cars" if n == 0 else f"{b} m {res['distance']['3d']['0.7'][b]:.2f} ({n} car") in out
    raw = res["pr_curve_raw"]  # the labels themselves: every car found at precision 1
    assert raw["recall"][-1] == 1.0 and set(raw["precision"]) == {1.0} and raw["score"] == [0.8]
