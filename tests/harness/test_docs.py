"""The documents' numbers are the sample's: README.md and docs/results.md hold, between their
``<!-- sample:NAME -->`` markers, exactly what ``harness.sample_docs`` writes from reports/sample/tables."""
import difflib
import shutil

import pandas as pd
import pytest

from harness import notes, sample_docs
from harness.core.kitti import KittiError
from harness.sample_docs import DOCUMENTS, ROOT, generated, render_blocks, update, write_docs
from harness.sample_numbers import MissingTable, num, span

SAMPLE_TABLES = ROOT / "reports" / "sample" / "tables"
PRESETS = {"ClearNoon": (0.0, "dry"), "WetNoon": (0.0, "wet"), "SoftRainNoon": (4.5, "rain"),
           "MidRainyNoon": (18.0, "rain"), "HardRainNoon": (50.0, "rain")}


# ----------------------------------------------------------------------------- the committed documents
@pytest.mark.parametrize("doc", list(DOCUMENTS))
def test_committed_documents_quote_the_sample_tables(doc):
    committed, expected, problems = generated(ROOT, SAMPLE_TABLES)[doc]
    assert problems == []  # every block there, each once, every table found
    diff = "".join(difflib.unified_diff(committed.splitlines(True), expected.splitlines(True), f"{doc} (committed)",
                                        f"{doc} (from {SAMPLE_TABLES.relative_to(ROOT)})"))
    assert committed == expected, f"{doc} differs from the sample's tables; `sotif-bench report --docs` rewrites " \
                                  f"it:\n{diff}"


def test_a_number_edited_by_hand_in_the_readme_table_is_caught():
    committed = (ROOT / "README.md").read_text(encoding="utf-8")
    row = next(line for line in committed.splitlines() if line.startswith("| PointPillars |"))
    edited = committed.replace(row, row.replace("| 79.4 |", "| 79.5 |"))  # PointPillars' val AP
    assert edited != committed
    restored, problems = update(edited, render_blocks(SAMPLE_TABLES), "README.md", DOCUMENTS["README.md"])
    assert problems == [] and restored == committed


# ----------------------------------------------------------------------------- tiny tables, known answers
def tiny_tables(folder):
    """Two models, five presets x 2 instances, a sweep of three instances (one no detector can pass)."""
    folder.mkdir(parents=True, exist_ok=True)
    models = {"pointpillars": (79.42, 59.79, 35.1, 3.91), "second": (90.81, 61.93, 80.6, 6.45)}
    pd.DataFrame([{"model": m, "val AP3D mod": v, "val frames": 300, "AP3D": ap} for m, (v, ap, _, _) in
                  models.items()]).to_csv(folder / "overview.csv", index=False)
    pd.DataFrame([{"model": m, "ort_p50_ms": ms, "size_mb": mb} for m, (_, _, ms, mb) in models.items()]) \
        .to_csv(folder / "runtime.csv", index=False)
    conds = [("dry", "dry", 20, 60), ("wet", "wet", 20, 60), ("rain", "rain", 60, 180),
             ("soft rain", "SoftRainNoon", 20, 60), ("mid rain", "MidRainyNoon", 20, 60),
             ("hard rain", "HardRainNoon", 20, 60)]
    pd.DataFrame([{"model": m, "iou": iou, "condition": c, "group": g, "n_frames": f, "n_car": n,
                   "ap": 80.0 - k - (10 if iou == 0.7 else 0) + (5 if m == "second" else 0)}
                  for m in models for iou in (0.5, 0.7) for k, (c, g, f, n) in enumerate(conds)]) \
        .to_csv(folder / "rain.csv", index=False)
    pd.DataFrame([{"weather": w, "n_test": 20, "rain_rate_mmh": r} for w, (r, _) in PRESETS.items()]) \
        .to_csv(folder / "data_by_weather.csv", index=False)
    pd.DataFrame([{"weather": w, "model": m, "n_frames": 20, "n_car": 60} for w in PRESETS for m in models]) \
        .to_csv(folder / "weather_detail.csv", index=False)
    pd.DataFrame([{"model": m, "n_corrupt_presets": 4} for m in models]).to_csv(folder / "robustness.csv", index=False)
    pd.DataFrame([{"model_a": "pointpillars", "model_b": "second", "metric": metric, "unit": unit, "n_units": n}
                  for metric, unit, n in (("val_ap3d_moderate", "frame", 300), ("headline_ap3d", "instance", 10))]) \
        .to_csv(folder / "pairs.csv", index=False)
    _instances(models).to_csv(folder / "sotif_instances.csv", index=False)
    return folder


def _instances(models) -> pd.DataFrame:
    scenario = {0: ("silver", "sedan", 90.0, 60.0), 1: ("nir_black", "suv", 99.7, 78.3)}
    rows = [{"set": "sotif", "instance_key": f"{w}#{i}", "weather": w, "instance": i, "sweep_axis": "preset",
             "precipitation_class": cls, "rain_rate_mmh": r, "fog_mor_m": 0.0, "road_water": 0.0,
             "sc_slow_paint": scenario[i][0], "sc_slow_body": scenario[i][1], "sc_ego_speed_kmh": scenario[i][2],
             "sc_slow_speed_kmh": scenario[i][3], "closing_speed_mps": 8.33, "feasible": True,
             "ideal_margin_m": 47.47 if i == 0 else 61.99, "margin": 33.0 if i == 0 else 52.0}
            for w, (r, cls) in PRESETS.items() for i in (0, 1)]
    rows += [{"set": "sweep", "instance_key": f"Sweep#{i}", "weather": "Sweep", "instance": i, "sweep_axis": axis,
              "precipitation_class": "rain" if axis == "rain" else "dry", "rain_rate_mmh": rain, "fog_mor_m": fog,
              "road_water": water, "sc_slow_paint": "white", "sc_slow_body": body, "sc_ego_speed_kmh": 100.0,
              "sc_slow_speed_kmh": 60.0, "closing_speed_mps": 11.11, "feasible": ideal >= 0, "ideal_margin_m": ideal,
              "margin": margin}
             for i, (axis, rain, fog, water, body, ideal, margin) in enumerate(
                 [("rain", 55.04, 0.0, 1.0, "van", 58.28, 57.16), ("fog", 0.0, 1514.9, 0.0, "hatchback", 21.45, -4.2),
                  ("water", 0.0, 0.0, 0.11, "hatchback", -5.3, None)])]
    out = []
    for m in models:
        for r in rows:
            margin = r["margin"] if m == "pointpillars" or r["set"] == "sotif" else None  # SECOND confirms no sweep car
            out.append({"model": m, **{k: v for k, v in r.items() if k != "margin"}, "margin_m": margin,
                        "pass": margin is not None and margin >= 0 and r["feasible"]})
    return pd.DataFrame(out)


def test_tiny_tables_give_the_known_readme_rows(tmp_path):
    text = render_blocks(tiny_tables(tmp_path / "tables"))["readme-table"]
    assert ("| PointPillars | 79.4 | 59.8 | 80.0 / 79.0 / 78.0 | 77.0 / 76.0 / 75.0 | 10/10 / 1/2 | 35 ms | 3.9 MB |"
            in text)
    assert "| SECOND | 90.8 | 61.9 | 85.0 / 84.0 / 83.0 | 82.0 / 81.0 / 80.0 | 10/10 / 0/2 | 81 ms | 6.5 MB |" in text
    words = " ".join(text.split())
    assert "(5 presets x 2 instances, 100 frames at 10 Hz in the deciding window, 300 cars)" in words
    assert "on the run's 300 held-out training-generator frames" in words
    assert "(20 / 20 / 60 frames, 60 / 60 / 180 cars)" in words and "(4.5 / 18 / 50 mm/h, 20 frames each)" in words
    assert "sweep: 3 instances over rain, fog visibility and road water, of which an ideal detector passes 2" in words


def test_tiny_tables_give_the_known_results_blocks(tmp_path):
    blocks = {k: " ".join(v.split()) for k, v in render_blocks(tiny_tables(tmp_path / "tables")).items()}
    assert ("the SOTIF set is 5 presets x 2 instances (the study's drive and one drawn from the scenario space: "
            "NIR-black SUV, ego 100 km/h, slow car 78 km/h), 100 frames with 300 cars") in blocks["data-sets"]
    assert ("3 instances, 1 per weather axis (drawn rain 55.0 mm/h, fog visibility 1,515 m, road water 0.11)"
            in blocks["data-sets"])
    assert "| Sweep#0 | rain 55.0 mm/h | white van | 40 km/h | 58.3 | 57.2 | - |" in blocks["sweep-instances"]
    assert "| Sweep#1 | fog 1,515 m | white hatchback | 40 km/h | 21.4 | -4.2 | - |" in blocks["sweep-instances"]
    assert "| Sweep#2 | water 0.11 | white hatchback | 40 km/h | -5.3 | - | - |" in blocks["sweep-instances"]
    assert ("every instance passes for every model (10/10): an ideal detector has 47.5 m to spare on the study's "
            "drive and 62.0 m to spare on the drawn one (NIR-black SUV, ego 100 km/h, slow car 78 km/h), and over "
            "the presets the models kept 33.0 m and 52.0 m.") in blocks["preset-margins"]
    assert "**val** = 300 held-out dry frames" in blocks["how-to-read"]
    assert "(dry / wet / rain 2 / 2 / 6)" in blocks["how-to-read"]
    assert "the val set's 300 frames for val AP and the SOTIF set's 10 instances" in blocks["how-to-read"]
    assert "over the 4 rain/wet presets" in blocks["how-to-read"]


def test_a_range_whose_ends_read_the_same_prints_once():
    assert span(68.2, 67.9) == "68" and span(31.84, 32.61, 1) == "31.8-32.6"
    assert num(1554) == "1,554" and num(-0.04, 1) == "0.0" and num(-0.06, 1) == "-0.1"
    rows = pd.DataFrame({"weather": ["A", "B"], "model": "m", "detected": True, "distance_m": [60.0, 60.2],
                         "distance_at_lane_change_m": [68.0, 68.0], "closing_speed_mps": 8.3,
                         "stopping_distance_m": 19.0, "verdict": "pass"})
    text = notes.sotif_leniency(rows)  # the report's SOTIF note
    assert "the slow car is 68 m ahead" in text and "detections came 60 m ahead" in text and "68-68" not in text


def test_the_report_says_what_each_interval_resamples(tmp_path):
    from harness import report_pairs
    pairs = pd.read_csv(tiny_tables(tmp_path / "tables") / "pairs.csv").assign(mean_diff=1.0, ci_lo=0.5, ci_hi=1.5,
                                                                               apart=True, data="d")
    intro = report_pairs.sections({"pairs": pairs}, {})[0][2]
    assert "resamples the 300 frames (val AP) and the 10 instances (SOTIF headline), the same for both" in intro
    assert "in an earlier sample (2026-11-27, docs/results.md, History) two draws differed" in intro


# ----------------------------------------------------------------------------- missing tables, markers
def test_a_missing_table_names_the_file_and_leaves_its_block(tmp_path):
    tables = tiny_tables(tmp_path / "tables")
    (tables / "runtime.csv").unlink()
    blocks = render_blocks(tables)
    assert isinstance(blocks["readme-table"], MissingTable)
    assert str(blocks["readme-table"]) == f"{tables / 'runtime.csv'}: table not found"
    assert isinstance(blocks["sweep-instances"], str)  # the blocks that do not need it are made
    doc = "intro\n<!-- sample:readme-table -->\nold numbers\n<!-- /sample -->\nend\n"
    text, problems = update(doc, blocks, "README.md")
    assert text == doc  # left as it was, not emptied
    assert problems == [f"README.md: block 'readme-table' left as it was: {tables / 'runtime.csv'}: table not found"]


def test_a_missing_column_names_the_file_and_the_column(tmp_path):
    tables = tiny_tables(tmp_path / "tables")
    pd.read_csv(tables / "sotif_instances.csv").drop(columns="feasible").to_csv(tables / "sotif_instances.csv",
                                                                              index=False)
    error = render_blocks(tables)["readme-table"]
    assert str(error) == f"{tables / 'sotif_instances.csv'}: no column 'feasible'"


def test_the_command_writes_the_documents_and_exits_2_on_a_missing_table(tmp_path, capsys):
    root = tmp_path / "repo"
    tables = tiny_tables(root / "reports" / "sample" / "tables")
    for rel, names in DOCUMENTS.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text("# doc\n\n" + "".join(f"<!-- sample:{n} -->\n<!-- /sample -->\n\n" for n in names)
                                + "hand-written\n")
    assert sample_docs.main(["--root", str(root)]) == 0
    assert "| PointPillars | 79.4 |" in (root / "README.md").read_text()
    assert (root / "docs" / "results.md").read_text().endswith("<!-- /sample -->\n\nhand-written\n")
    assert sample_docs.main(["--root", str(root), "--check"]) == 0
    assert write_docs(root) == ([], [])  # nothing left to change
    (tables / "pairs.csv").unlink()
    capsys.readouterr()
    assert sample_docs.main(["--root", str(root)]) == 2
    err = capsys.readouterr().err
    assert f"docs/results.md: block 'how-to-read' left as it was: {tables / 'pairs.csv'}: table not found" in err


def test_a_stale_document_fails_the_check(tmp_path, capsys):
    root = tmp_path / "repo"
    shutil.copytree(SAMPLE_TABLES, root / "reports" / "sample" / "tables")
    for rel in DOCUMENTS:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(ROOT / rel, root / rel)
    readme = root / "README.md"
    readme.write_text(readme.read_text().replace("1,554 frames", "492 frames", 1))
    assert sample_docs.main(["--root", str(root), "--check"]) == 2
    assert "README.md: differs from the sample's tables" in capsys.readouterr().err
    assert sample_docs.main(["--root", str(root)]) == 0
    assert readme.read_text() == (ROOT / "README.md").read_text()


@pytest.mark.parametrize("doc, problem", [
    ("<!-- sample:nonsense -->\n<!-- /sample -->\n", "x.md:1: unknown block 'nonsense'"),
    ("a\n<!-- sample:data-sets -->\nb\n", "x.md:2: block 'data-sets' is not closed"),
    ("a\n<!-- /sample -->\n", "x.md:2: <!-- /sample --> closes no block"),
    ("<!-- sample:data-sets -->\n<!-- sample:how-to-read -->\n", "x.md:2: block 'data-sets' opened on line 1"),
])
def test_broken_markers_name_the_document_and_line(doc, problem):
    with pytest.raises(KittiError, match=problem.replace("(", r"\(")):
        update(doc, {}, "x.md")


def test_an_expected_block_missing_or_twice_is_a_problem():
    blocks = {"data-sets": "new"}
    doc = "<!-- sample:data-sets -->\nold\n<!-- /sample -->\n<!-- sample:data-sets -->\n<!-- /sample -->\n"
    text, problems = update(doc, blocks, "x.md", ("data-sets", "how-to-read"))
    assert text == "<!-- sample:data-sets -->\nnew\n<!-- /sample -->\n" * 2
    assert problems == ["x.md: no block 'how-to-read' (mark it <!-- sample:how-to-read --> ... <!-- /sample -->)",
                        "x.md: block 'data-sets' appears 2 times"]
