import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness import report
from harness.cli import main
from harness.core import kitti
from harness.core.files import atomic_write_text
from harness.core.kitti import KittiError, Labels
from harness.evaluate import evaluate, write_results
from harness.sotif import sotif_view

WEATHERS = {"ClearNoon": ("Noon", "dry"), "ClearSunset": ("Sunset", "dry"), "HardRainNight": ("Night", "rain")}
FACTS = {"ClearNoon": (5.0, 0.0, 0.0, 0.0, 0.0), "ClearSunset": (5.0, 0.0, 0.0, 0.0, 0.0),  # cloudiness, precipitation,
         "HardRainNight": (100.0, 100.0, 90.0, 100.0, 50.0)}  # deposits, wetness, rain mm/h (simulator.weather)
FACT_COLUMNS = ("cloudiness", "precipitation", "precipitation_deposits", "wetness", "rain_rate_mmh")


def _frame(rng, data, fid, k):
    """Slow car ahead in the ego lane (label row 0) and two other cars; a small scan around them."""
    calib = kitti.kitti_calib()
    boxes = np.array([[55.0 - 3 * k, 0.0, -0.9, 4.75, 1.83, 1.45, 0.0], [25.0, 3.6, -0.9, 4.2, 1.8, 1.5, 0.0],
                      [40.0, -3.6, -0.9, 4.4, 1.8, 1.5, 0.05]], np.float32)
    pts = np.concatenate([np.c_[rng.uniform(-0.5, 0.5, (150, 3)) * b[3:6] + b[:3], rng.uniform(0, 1, 150)] for b in boxes])
    kitti.write_points(kitti.frame_path(data, "velodyne", fid), pts.astype(np.float32))
    kitti.write_calib(kitti.frame_path(data, "calib", fid), calib)
    kitti.write_labels(kitti.frame_path(data, "label_2", fid), Labels.from_lidar(boxes, calib, ["Car"] * 3))
    return boxes, calib


def _predict(rng, out, fid, boxes, calib, quality, two_stage):
    dets = boxes + np.c_[rng.normal(0, quality, (len(boxes), 2)), np.zeros((len(boxes), 5))]
    scores = rng.uniform(0.4, 0.95, len(boxes))
    kitti.write_labels(out / f"{fid}.txt", Labels.from_lidar(dets, calib, ["Car"] * len(dets), score=scores))
    if two_stage:
        kitti.write_labels(out / "rois" / f"{fid}.txt", Labels.from_lidar(dets, calib, ["Car"] * len(dets), score=scores))


def make_run(root, models=(("alpha", 0.1, False), ("beta", 0.6, True)), sotif_columns=True):
    """A run directory as the pipeline writes it, with tiny data and real evaluation results."""
    rng = np.random.default_rng(0)
    data = root / "data" / "sotif"
    rows = []
    for w_i, (weather, (tod, precip)) in enumerate(WEATHERS.items()):
        for k in range(4):
            fid = f"{4 * w_i + k:06d}"
            boxes, calib = _frame(rng, data, fid, k)
            for name, quality, two_stage in models:
                folder = "predictions_val" if k == 0 else "predictions"
                _predict(rng, root / folder / name, fid, boxes, calib, quality * (1 + w_i), two_stage)
            rows.append({"frame_id": fid, "split": "val" if k == 0 else "test", "weather": weather, "time_of_day": tod,
                         "precipitation_class": precip, "scenario_time_s": 0.5 * k, "lane_change_time_s": 0.5,
                         "slow_car_label_index": 0, "ego_speed_mps": 25.0, "slow_car_speed_mps": 16.7,
                         "n_points": 450, **dict(zip(FACT_COLUMNS, FACTS[weather]))})
    meta = pd.DataFrame(rows)
    if not sotif_columns:
        meta = meta[["frame_id", "split", "weather", "time_of_day", "precipitation_class", "n_points"]]
    kitti.write_frames_meta(data / "meta" / "frames.csv", meta)
    for split in ("test", "val"):
        kitti.write_image_set(data / "ImageSets" / f"{split}.txt", [r["frame_id"] for r in rows if r["split"] == split])
    summary = {}
    for name, _, two_stage in models:
        res = evaluate(data, root / "predictions" / name, split=data / "ImageSets" / "test.txt",
                       group_by=["weather", "time_of_day", "precipitation_class"], meta=data / "meta" / "frames.csv",
                       n_bootstrap=5)
        write_results(root / "results" / f"{name}.json", res)
        summary[name] = {"architecture": name.upper(), "two_stage": two_stage, "uses_camera": False,
                         "onnx": f"models/{name}.onnx", "size_mb": 3.2, "params": 1_200_000,
                         "train": {"seconds": 5.0, "epochs": 2, "final_loss": 0.5},
                         "runtime": {"onnxruntime": {"latency_ms_p50": 40.0 * (1 + two_stage), "latency_ms_p90": 50.0, "fps": 22.0},
                                     "torch_eager_ms_p50": 90.0, "ort_speedup": 2.2, "peak_memory_mb": 310.0,
                                     "agreement": {"same_boxes": 1.0, "max_abs_score_diff": 2e-6}},
                         "results": f"results/{name}.json"}
        if sotif_columns:
            summary[name]["sotif"] = sotif_view(data, root / "predictions" / name,
                                                val_predictions_dir=root / "predictions_val" / name)
    doc = {"schema": "sotif-bench/run/1", "profile": "quick", "created": "2026-01-01T00:00:00+00:00", "models": summary,
           "data": {"n_test_frames": 9, "n_val_frames": 3, "n_train_frames": 40, "stats": "tables/data_stats.csv"},
           "stage_seconds": {"simulate_sotif": 12.5, "train_alpha": 30.0}}
    atomic_write_text(root / "results.json", json.dumps(doc))
    return root


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A rendered run: (run directory, index.html bytes)."""
    root = make_run(tmp_path_factory.mktemp("run"))
    index = report.render(root)
    assert index == root / "index.html"
    return root, index.read_bytes()


def test_render_writes_a_self_contained_report(rendered):
    html = rendered[1].decode("utf-8")
    assert not re.search(r"https?://|<script|<link", html)
    srcs = re.findall(r'src="([^"]*)"', html)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert len(srcs) == 9  # rain, heatmap, relative to clear, AP/latency, PR curves, AP/distance, data, BEV, paired differences
    # the reader sees what was run, then the rain story, the models, the heatmaps, the main table, then the rest
    pos = [html.index(s) for s in ("profile</b> quick", "alpha, beta", 'id="rain"', 'alt="rain"',
                                   "<h2>Models at a glance", 'alt="heatmap"', 'alt="heatmap_delta"', "HardRainNight",
                                   'id="paper"')]
    assert pos == sorted(pos)
    assert 'id="sotif"' in html and "Recall of two-stage models" in html
    assert re.search(r'<td class="(pass|fail)">(pass|FAIL) ', html)
    # cells read as in report.md: booleans as yes / no, missing values as a dash
    cells = re.findall(r"<td[^>]*>([^<]*)</td>", html)
    assert not {"None", "nan", "True", "False"} & set(cells) and {"yes", "no"} <= set(cells)


def test_report_md_links_written_figures_and_tables(rendered):
    run_dir = rendered[0]
    md = (run_dir / "report.md").read_text()
    links = re.findall(r"\]\((figures/[^)]+)\)", md)
    assert links and all((run_dir / link).is_file() for link in links)
    assert md.startswith("# sotif-bench report: profile quick")
    assert "| weather | alpha | beta |" in md
    for name in ("kitti_ap", "weather_headline", "sotif", "runtime", "robustness"):
        assert (run_dir / "tables" / f"{name}.csv").is_file()
    main = pd.read_csv(run_dir / "tables" / "weather_headline.csv")
    res = json.loads((run_dir / "results" / "alpha.json").read_text())
    for weather, row in res["groups_by"]["weather"]["rows"].items():
        # rounded to 4 decimals as the CSV is written
        assert main.loc[main.weather == weather, "alpha"].item() == round(row["headline"]["3d"]["0.7"], 4)
        assert f"{row['headline']['3d']['0.7']:.1f} [" in md


def test_render_is_deterministic(rendered):
    run_dir, first = rendered
    assert report.render(run_dir).read_bytes() == first


def test_optional_parts_are_skipped(tmp_path):
    root = make_run(tmp_path, models=(("alpha", 0.1, False),), sotif_columns=False)
    (root / "data" / "sotif" / "meta" / "frames.csv").unlink()  # no data meta at all
    html = report.render(root).read_text()
    assert 'id="sotif"' not in html and "Recall of two-stage models" in html  # heading kept, table says so
    assert "(not available in this run)" in html and 'alt="bev"' not in html
    assert 'alt="heatmap"' in html


@pytest.mark.parametrize("content,message", [(None, "file not found"), ("{broken", "not valid JSON"),
                                              ('{"schema": "sotif-bench/run/1", "models": {}}', "no models")])
def test_bad_results_json_names_the_file_and_writes_nothing(tmp_path, content, message):
    if content is not None:
        (tmp_path / "results.json").write_text(content)
    with pytest.raises(KittiError, match=f"results.json: {message}"):
        report.render(tmp_path)
    assert not (tmp_path / "index.html").exists() and not (tmp_path / "tables").exists()


@pytest.fixture(scope="module")
def unrendered(tmp_path_factory):
    """A run that has not been rendered yet (no tables, figures or report)."""
    return make_run(tmp_path_factory.mktemp("unrendered"))


def _set(doc: dict, keys: str, value) -> None:
    *parents, last = keys.split("/")
    for k in parents:
        doc = doc[k]
    doc[last] = value


@pytest.mark.parametrize("file,keys,value,message", [
    ("results/alpha.json", "kitti", None, "'kitti' is null, expected an object"),
    ("results/alpha.json", "headline/3d/0.7", "62.5", "'headline.3d.0.7' is a string, expected a number"),
    ("results/beta.json", "groups_by/weather/rows/ClearNoon/headline/bev/0.7", "62.5",
     "'groups_by.weather.rows.ClearNoon.headline.bev.0.7' is a string, expected a number"),
    ("results/alpha.json", "groups_by/weather/rows/ClearNoon/headline_ci95/3d", [1.0],
     "'groups_by.weather.rows.ClearNoon.headline_ci95.3d' is a list of 1, expected a list of 2"),
    ("results.json", "models/alpha/sotif", [1, 2], "'models.alpha.sotif' is a list, expected an object"),
    ("results.json", "models/beta/runtime", "x", "'models.beta.runtime' is a string, expected an object"),
    ("results.json", "models/alpha/params", True, "'models.alpha.params' is true, expected a number or null"),
    ("results.json", "wall_seconds", "12 s", "'wall_seconds' is a string, expected a number or null"),
])
def test_a_value_of_the_wrong_type_names_the_file_and_key_and_writes_nothing(unrendered, tmp_path, capsys, file, keys,
                                                                             value, message):
    root = Path(shutil.copytree(unrendered, tmp_path / "run"))
    doc = json.loads((root / file).read_text())
    _set(doc, keys, value)
    (root / file).write_text(json.dumps(doc))
    with pytest.raises(KittiError, match=re.escape(f"{root / file}: {message}")):
        report.render(root)
    assert main(["--quiet", "report", str(root)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"sotif-bench report: error: {root / file}: {message}") and "Traceback" not in err
    assert not (root / "index.html").exists() and not (root / "report.md").exists()
    assert not (root / "tables").exists() and not (root / "figures").exists()


def test_report_reads_on_its_own(rendered):
    """No file outside the report is cited, headers are words, each section says how to read it, and a
    quick run carries the smoke-run banner."""
    run_dir, html = rendered[0], rendered[1].decode("utf-8")
    md = (run_dir / "report.md").read_text()
    for text in (html, md):
        assert "DESIGN.md" not in text and "README" not in text
        assert "Smoke run: numbers meaningless." in text
    headers = re.findall(r"<th>([^<]*)</th>", html)
    assert headers and not [h for h in headers if "_" in h]  # the fake run's model names have no underscore
    assert html.count('<p class="read"><b>How to read:</b>') == html.count("<h2>") == md.count("\n## ")
    assert html.count('<div class="tablebox"><table') == html.count("<table")


def test_navigation_lists_the_sections_in_their_order(rendered):
    html = rendered[1].decode("utf-8")
    nav = re.search(r"<nav>(.*?)</nav>", html, re.S).group(1)
    links = re.findall(r'<a href="#([^"]+)">([^<]*)</a>', nav)
    sections = re.findall(r'<section id="([^"]+)">\s*<h2>([^<]*)</h2>', html)
    assert links == sections and ("models", "Models at a glance") in links


def test_only_a_quick_run_has_the_banner(tmp_path):
    root = make_run(tmp_path)
    doc = json.loads((root / "results.json").read_text())
    atomic_write_text(root / "results.json", json.dumps({**doc, "profile": "default"}))
    report.render(root)
    assert "Smoke run" not in (root / "index.html").read_text() and "Smoke run" not in (root / "report.md").read_text()


def test_capped_and_empty_aps_read_as_such_in_both_reports(rendered):
    from harness.cells import binds, cap
    run_dir, html = rendered[0], rendered[1].decode("utf-8")
    md = (run_dir / "report.md").read_text()
    expected = set()
    for row in pd.read_csv(run_dir / "tables" / "weather_detail.csv").to_dict("records"):
        for b in ("0-30", "30-50", "50-80"):
            n, v = int(row[f"n_gt_{b}m"]), row[f"ap3d_{b}m"]
            expected.add("n/a (0 cars)" if n == 0 else f"{v:.1f} (≤ {cap(n):.1f})" if binds(n) else f"{v:.1f}")
    assert any("(" in e for e in expected)  # 9 test frames: capped or empty bins
    for text in (md, html):
        assert all(e in text for e in expected)


def test_sotif_leniency_states_the_slack_from_the_rows():
    from harness import notes, tables
    rows = pd.DataFrame({"weather": ["A", "B", "C"], "model": "m", "detected": [True, True, False],
                         "distance_m": [52.0, 47.5, None], "distance_at_lane_change_m": [61.0, 46.0, 46.0],
                         "closing_speed_mps": [8.0, 8.0, 8.0], "stopping_distance_m": [19.0, 19.0, 19.0],
                         "verdict": ["pass", "pass", "FAIL"]})
    text = notes.sotif_leniency(rows)
    slack = (46.0 - 19.0) / 8.0
    assert "46-61 m ahead" in text and "needs 19 m" in text and f"up to {slack:.1f} s" in text
    assert "2 of 3 cells pass" in text and "detections came 48-52 m ahead" in text
    assert notes.sotif_leniency(pd.DataFrame(columns=tables.SOTIF_COLUMNS)) == ""


def test_lidar_fog_and_val_notes(tmp_path):
    from harness import notes
    meta = pd.DataFrame({"weather": ["ClearNoon", "ClearNight", "HardRainNoon"], "time_of_day": ["Noon", "Night", "Noon"],
                         "rain_rate_mmh": [0.0, 0.0, 50.0], "precipitation": [0.0, 0.0, 100.0],
                         "precipitation_deposits": [0.0, 0.0, 90.0], "wetness": [0.0, 0.0, 100.0],
                         "cloudiness": [5.0, 5.0, 100.0]})
    text = notes.lidar_twins_note(meta)
    assert "tells 2 conditions apart among these 3 presets" in text and "ClearNoon = ClearNight" in text
    assert notes.lidar_twins_note(None) == "" and notes.fog_note(None) == ""
    assert "No preset of this run has LiDAR fog" in notes.fog_note(meta)
    assert notes.fog_note(meta.assign(lidar_fog_mor_m=[0.0, 0.0, 200.0])) == "Presets with LiDAR fog: HardRainNoon."
    kitti.write_image_set(tmp_path / "data" / "train" / "ImageSets" / "val.txt", ["000001", "000002"])
    vals = notes.val_sets(tmp_path, {"data": {"n_val_frames": 7}})
    assert vals == {"sotif": 7, "training": 2, "valset": None}
    assert "on 2 held-out dry frames" in notes.val_note(vals) and "the 7 val frames" in notes.val_note(vals)
    assert "SOTIF val 7 (operating thresholds)" in notes.val_header(vals)
    kitti.write_image_set(tmp_path / "data" / "val_frames.txt", [f"{i:06d}" for i in range(5)])
    vals = notes.val_sets(tmp_path, {"data": {"n_val_frames": 0}})
    assert vals["valset"] == 5 and notes.val_header(vals) == "val set 5 (val AP and operating thresholds)"
    assert "the run's 5 held-out frames" in notes.val_note(vals) and "operating threshold" in notes.val_note(vals)


def test_report_leads_with_the_rain_story_and_says_what_its_numbers_do_not(rendered):
    run_dir, html = rendered[0], rendered[1].decode("utf-8")
    md = (run_dir / "report.md").read_text()
    assert md.index("## Which detectors hold up in rain") < md.index("## Models at a glance")
    rain = pd.read_csv(run_dir / "tables" / "rain.csv", dtype={"iou": str})
    res = json.loads((run_dir / "results" / "beta.json").read_text())
    dry = res["groups_by"]["precipitation_class"]["rows"]["dry"]
    row = rain[(rain.model == "beta") & (rain.condition == "dry") & (rain.iou == "0.5")].iloc[0]
    # the CSV keeps 4 decimals
    assert row.ap == pytest.approx(dry["headline"]["3d"]["0.5"], abs=1e-4)
    assert row.ap_lo == pytest.approx(dry["headline_ci95_0.5"]["3d"][0], abs=1e-4)
    assert f"| beta | 0.5 | {row.ap:.1f} [{row.ap_lo:.1f}, {row.ap_hi:.1f}] |" in md
    for text in (html, md):
        assert "SOTIF val 3 (operating thresholds)" in text and "How lenient this is" in text
        assert "No preset of this run has LiDAR fog" in text and "tells 2 conditions apart" in text
        assert "the run does not record the code" in text  # the fake run predates the record
    assert "worst rain/wet preset" in html and "ClearNoon</td><td>" not in html.split('id="robustness"')[1][:3000]
