"""The documents' numbers are the sample's: README.md and docs/results.md hold, between their
``<!-- sample:NAME -->`` markers, exactly what ``harness.sample_docs`` writes from reports/sample/tables."""
import difflib
import re
import shutil

import pandas as pd
import pytest

from harness import notes, sample_docs
from harness.core.kitti import KittiError
from harness.sample_docs import DOCUMENTS, ROOT, generated, render_blocks, update, write_docs
from harness.sample_numbers import APART, MissingTable, num, span

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
    cells = row.split(" | ")
    val = cells[1].split(" ")[0]  # "76.8", or "70.7 (61.2-75.7)" in a sample of draws: the mean first
    cells[1] = cells[1].replace(val, f"{float(val) + 0.1:.1f}", 1)  # PointPillars' val AP, edited
    edited = committed.replace(row, " | ".join(cells))
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
    pd.DataFrame([{"model": m, "ort_p50_ms": ms, "ort_p90_ms": 1.5 * ms, "size_mb": mb}
                  for m, (_, _, ms, mb) in models.items()]).to_csv(folder / "runtime.csv", index=False)
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
    pd.DataFrame([{"model_a": "pointpillars", "model_b": "second", "metric": metric, "unit": unit, "n_units": n,
                   "mean_diff": diff, "ci_lo": diff - 2.0, "ci_hi": diff + 2.0, "apart": apart, "n_draws_a": 1,
                   "n_draws_b": 1}
                  for metric, unit, n, diff, apart in (("val_ap3d_moderate", "frame", 300, -11.39, True),
                                                       ("headline_ap3d", "instance", 10, -2.14, False))]) \
        .to_csv(folder / "pairs.csv", index=False)
    pd.DataFrame([{"set": "sotif", "verdict": v, "model_a": "pointpillars", "model_b": "second", "a_only": 0,
                   "b_only": 0, "apart": False} for v in ("perception", "system")]) \
        .to_csv(folder / "sotif_pairs.csv", index=False)
    _instances(models).to_csv(folder / "sotif_instances.csv", index=False)
    # the pass rates as harness.report_space writes them (the intervals made up: the blocks only print them)
    rates = [("pointpillars", "sweep", "perception", "car", 1, 1, 0.21, 1.0), ("pointpillars", "sweep", "system", "car", 0, 1, 0.0, 0.79),
             ("pointpillars", "sweep", "perception", APART, 1, 1, 0.21, 1.0), ("second", "sweep", "perception", "car", 0, 1, 0.0, 0.79),
             ("second", "sweep", "system", "car", 0, 1, 0.0, 0.79), ("second", "sweep", "perception", APART, 0, 1, 0.0, 0.79),
             *((m, "sotif", v, "car", 10, 10, 0.72, 1.0) for m in models for v in ("perception", "system"))]
    pd.DataFrame([{"model": m, "set": s, "verdict": v, "body_class": b, "column": "all", "bin": "all", "n": n,
                   "n_pass": k, "lo": lo, "hi": hi} for m, s, v, b, k, n, lo, hi in rates]) \
        .to_csv(folder / "sotif_pass_rates.csv", index=False)
    pd.DataFrame([{"model": m, "set": s, "weather": "ClearNoon", "hours": 0.005, "n_false": 1 if m == "pointpillars" else 0}
                  for m in models for s in ("sotif", "sweep")]).to_csv(folder / "sotif_phantoms.csv", index=False)
    pd.DataFrame([{"model": m, "axis": "rain", "scenario": "120-60_sedan_silver", "lo": 25.0, "hi": 50.0, "unit": "mm/h",
                   "status": "bracketed" if m == "pointpillars" else "passes everywhere", "n_probes": 3}
                  for m in models]).to_csv(folder / "sotif_boundaries.csv", index=False)
    return folder


def _instances(models) -> pd.DataFrame:
    """Per model the perception and system rows (harness.verdict's columns) of 5 presets x 2 drives and a sweep of
    three: a van in rain, a hatchback in fog, an unpreventable hatchback on a wet road (range)."""
    scenario = {0: ("silver", "sedan", 0.57, 0.5), 1: ("nir_black", "suv", 0.6, 0.3)}  # paint, body, reflectance, ref a_req
    rows = [{"set": "sotif", "instance": f"{w}#{i}", "weather": w, "sweep_axis": "preset", "precipitation_class": cls,
             "rain_mm_h": r, "fog_mor_m": 0.0, "water": 0.0, "paint": scenario[i][0], "body": scenario[i][1],
             "reflectance": scenario[i][2], "body_class": "car", "preventable": True, "reason": None,
             "reference_confirm_s": 1.0, "reference_a_req_mps2": scenario[i][3],
             "hit": (1.1, 0.1, scenario[i][3] + 0.1)} for w, (r, cls) in PRESETS.items() for i in (0, 1)]
    rows += [{"set": "sweep", "instance": f"Sweep#{i}", "weather": "Sweep", "sweep_axis": axis,
              "precipitation_class": "rain" if axis == "rain" else "dry", "rain_mm_h": rain, "fog_mor_m": fog,
              "water": water, "paint": "white", "body": body, "reflectance": 0.6,
              "body_class": APART if body == "van" else "car", "preventable": reason is None, "reason": reason,
              "reference_confirm_s": ref[0], "reference_a_req_mps2": ref[1], "hit": hit}
             for i, (axis, rain, fog, water, body, reason, ref, hit) in enumerate(
                 [("rain", 55.04, 0.0, 1.0, "van", None, (1.6, 0.17), (3.1, 1.5, 0.19)),
                  ("fog", 0.0, 1514.9, 0.0, "hatchback", None, (1.8, 1.85), (2.0, 0.2, 2.46)),
                  ("water", 0.0, 0.0, 0.11, "hatchback", "range", (3.1, 7.78), None)])]
    out = []
    for m in models:
        for r in rows:  # SECOND confirms no sweep vehicle
            hit = r["hit"] if m == "pointpillars" or r["set"] == "sotif" else None
            for verdict in ("perception", "system"):
                confirm, delay, a_req = hit if hit else (None, None, float("inf"))
                out.append({"model": m, **{k: v for k, v in r.items() if k != "hit"}, "verdict": verdict,
                            "confirm_s": confirm, "delay_s": delay, "a_req_mps2": a_req,
                            "passed": a_req <= 6.0 and r["preventable"]})
    return pd.DataFrame(out)


def test_tiny_tables_give_the_known_readme_rows(tmp_path):
    text = render_blocks(tiny_tables(tmp_path / "tables"))["readme-table"]
    assert ("| PointPillars | 79.4 | 59.8 | 80.0 / 79.0 / 78.0 | 77.0 / 76.0 / 75.0 | 1/1 (0.21-1.00) | 0/1 | 1/1 | "
            "10/10 | 200/h | 35 / 53 ms | 3.9 MB |") in text
    assert ("| SECOND | 90.8 | 61.9 | 85.0 / 84.0 / 83.0 | 82.0 / 81.0 / 80.0 | 0/1 (0.00-0.79) | 0/1 | 0/1 | 10/10 | "
            "0/h | 81 / 121 ms | 6.5 MB |") in text
    words = " ".join(text.split())
    assert "(5 presets x 2 drives, 100 frames at 10 Hz in the deciding window, 300 cars)" in words
    assert "on the run's 300 held-out training-generator frames" in words
    assert "(20 / 20 / 60 frames, 60 / 60 / 180 cars)" in words and "(4.5 / 18 / 50 mm/h, 20 frames each)" in words
    assert ("of the 3 sweep instances (one of rain, fog visibility and road water moved, the scenario drawn), the 1 "
            "car-bodied ones (of 2) a reference perception could pass") in words
    assert "Vans, trucks: the 1 sweep instances whose slow vehicle is outside the Car class" in words
    bounds = render_blocks(tiny_tables(tmp_path / "again"))["boundaries"]
    assert "| rain (mm/h), 120-60 sedan silver | fails above 25-50 mm/h | passes everywhere in 25-50 mm/h |" in bounds
    assert "each of 1 weather and paint axes moved alone on 1 reference scenarios (3 probes" in " ".join(bounds.split())


def test_tiny_tables_give_the_known_rankings(tmp_path):
    """The README's ranking sentences name exactly the pairs apart in pairs.csv and sotif_pairs.csv."""
    words = " ".join(render_blocks(tiny_tables(tmp_path / "tables"))["rankings"].split())
    assert "a bootstrap over the same 300 val frames and 10 SOTIF instances for both models; one training draw each" \
        in words
    assert ("On val AP: SECOND above PointPillars (by 11.4 points). On the SOTIF headline AP @0.7: no pair is apart. "
            "On the SOTIF verdict") in words
    assert words.endswith("p < 0.05), no pair is apart.")


def test_rankings_over_draws_name_each_winner_once_with_its_range(tmp_path):
    """Three models, three draws each: a model above both others is above "every other model"; the others' wins
    follow, most first (then in the models table's order); a pair whose interval spans 0 is not named; a verdict
    pair apart names the one that passes more."""
    folder = tiny_tables(tmp_path / "tables")
    pd.DataFrame([{"model": m, "val AP3D mod": 80.0, "val frames": 300, "AP3D": 60.0}
                  for m in ("pointpillars", "second", "parta2")]).to_csv(folder / "overview.csv", index=False)
    rows = [("pointpillars", "second", "val_ap3d_moderate", -4.04, True), ("pointpillars", "parta2", "val_ap3d_moderate",
            -6.96, True), ("second", "parta2", "val_ap3d_moderate", -0.5, False),
            ("pointpillars", "second", "headline_ap3d", 3.0, True), ("pointpillars", "parta2", "headline_ap3d", 1.0, False),
            ("second", "parta2", "headline_ap3d", -2.25, True)]
    pd.DataFrame([{"model_a": a, "model_b": b, "metric": m, "unit": "frame" if m.startswith("val") else "instance",
                   "n_units": 300 if m.startswith("val") else 42, "mean_diff": d, "ci_lo": d - 1.0, "ci_hi": d + 1.0,
                   "apart": ap, "n_draws_a": 3, "n_draws_b": 3} for a, b, m, d, ap in rows]).to_csv(folder / "pairs.csv",
                                                                                                index=False)
    pd.DataFrame([{"set": "sweep", "verdict": "perception", "model_a": "pointpillars", "model_b": "parta2",
                   "a_only": 1, "b_only": 9, "apart": True},
                  {"set": "sweep", "verdict": "system", "model_a": "pointpillars", "model_b": "parta2", "a_only": 2,
                   "b_only": 5, "apart": False}]).to_csv(folder / "sotif_pairs.csv", index=False)
    words = " ".join(render_blocks(folder)["rankings"].split())
    assert "for both models and over their 3 training draws each" in words and "one training draw each" not in words
    assert "On val AP: SECOND above PointPillars (by 4.0 points); Part-A2 above PointPillars (by 7.0 points)." in words
    assert ("On the SOTIF headline AP @0.7: PointPillars above SECOND (by 3.0 points); Part-A2 above SECOND "
            "(by 2.2 points).") in words
    assert ("Part-A2 passes more of the sweep instances than PointPillars (perception: 9 against 1 passed by one of "
            "the two only).") in words and "system:" not in words
    rows[1] = ("pointpillars", "parta2", "val_ap3d_moderate", -6.96, True)
    rows[2] = ("second", "parta2", "val_ap3d_moderate", -1.5, True)
    pd.DataFrame([{"model_a": a, "model_b": b, "metric": m, "unit": "frame", "n_units": 300, "mean_diff": d,
                   "ci_lo": d - 1.0, "ci_hi": d + 1.0, "apart": ap, "n_draws_a": 3, "n_draws_b": 3}
                  for a, b, m, d, ap in rows[:3]]) \
        .to_csv(folder / "pairs.csv", index=False)
    words = " ".join(render_blocks(folder)["rankings"].split())
    assert ("On val AP: Part-A2 above every other model (by 1.5-7.0 points); SECOND above PointPillars (by 4.0 "
            "points). On the SOTIF verdict") in words


def test_the_readme_table_of_a_sample_of_draws_gives_their_mean_and_range(tmp_path):
    """With tables/draws.csv of 3 draws: val and AP @0.7 are mean (min-max), said so with the seeds; the other
    columns stay the first draw's. A headline bootstrapped over SOTIF frames is not called val frames."""
    folder = tiny_tables(tmp_path / "tables")
    pd.DataFrame([{"model": "pointpillars", "draws": 3, "seeds": "0,1,2", "val AP3D mod mean": 78.234,
                   "val AP3D mod min": 76.85, "val AP3D mod max": 79.42, "AP3D mean": 60.0, "AP3D min": 58.74,
                   "AP3D max": 61.26}]).to_csv(folder / "draws.csv", index=False)
    pairs = pd.read_csv(folder / "pairs.csv")
    pairs.loc[pairs["metric"] == "headline_ap3d", ["unit", "n_units"]] = ["frame", 3654]
    pairs.to_csv(folder / "pairs.csv", index=False)
    blocks = render_blocks(folder)
    text = blocks["readme-table"]
    assert "| PointPillars | 78.2 (76.8-79.4) | 60.0 (58.7-61.3) | 80.0 / 79.0 / 78.0 |" in text
    assert "| SECOND | 90.8 | 61.9 |" in text  # a model without a draws row keeps its own
    words = " ".join(text.split())
    assert ("val and AP @0.7: the mean (min-max) over 3 training draws per model (seeds 0-2; `tables/draws.csv`); "
            "every other column is the first draw's (seed 0).") in words
    assert "the same 300 val frames and 3,654 SOTIF frames for both models" in " ".join(blocks["rankings"].split())
    pairs.assign(n_draws_a=3, n_draws_b=3).to_csv(folder / "pairs.csv", index=False)
    assert ("the SOTIF set's 3,654 frames for the headline, and each model's 3 training draws (each replicate draws "
            "one per model, then the frames).") in " ".join(render_blocks(folder)["how-to-read"].split())
    pd.read_csv(folder / "draws.csv").assign(draws=1, seeds="0").to_csv(folder / "draws.csv", index=False)
    assert "| PointPillars | 79.4 | 59.8 |" in render_blocks(folder)["readme-table"]  # one draw: as without


def test_tiny_tables_give_the_known_results_blocks(tmp_path):
    blocks = {k: " ".join(v.split()) for k, v in render_blocks(tiny_tables(tmp_path / "tables")).items()}
    assert ("the SOTIF set is 5 presets x 2 drives (the study's drive and one drawn from the scenario space, its "
            "slow vehicle a NIR-black SUV, reflectance 0.60), 100 frames with 300 cars") in blocks["data-sets"]
    assert ("3 instances, 1 per weather axis (drawn rain 55.0 mm/h, fog visibility 1,515 m, road water 0.11)"
            in blocks["data-sets"])
    assert "2 car-bodied slow vehicles, 1 of them preventable (unpreventable: 1 range), and 1 vans" in blocks["data-sets"]
    assert ("| Sweep#0 | rain 55.0 mm/h | white van, reflectance 0.60 | yes | 1.6 s, 0.2 | 0.2 | never |"
            in blocks["sweep-instances"])
    assert ("| Sweep#1 | fog 1,515 m | white hatchback, reflectance 0.60 | yes | 1.8 s, 1.9 | 2.5 | never |"
            in blocks["sweep-instances"])
    assert ("| Sweep#2 | water 0.11 | white hatchback, reflectance 0.60 | no: range | 3.1 s, 7.8 | – | – |"
            in blocks["sweep-instances"])
    assert ("On the 5 presets (10 instances, 10 preventable; unpreventable: none) every model passes 10/10 in "
            "perception and 10/10 as a system. The reference needs 0.5 m/s^2 on the study's drive and 0.3 m/s^2 on "
            "the drawn one (NIR-black SUV, reflectance 0.60); the models' decisions need 0.4-0.6 m/s^2, 0.10 s "
            "behind the reference.") in blocks["preset-verdict"]
    assert "**val** = 300 held-out dry frames" in blocks["how-to-read"]
    assert "(dry / wet / rain 2 / 2 / 6)" in blocks["how-to-read"]
    assert "the val set's 300 frames for val AP and the SOTIF set's 10 instances" in blocks["how-to-read"]
    assert "over the 4 rain/wet presets" in blocks["how-to-read"]
    assert "preventable car-bodied instances (1 of 2)" in blocks["how-to-read"]


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
    pd.read_csv(tables / "sotif_instances.csv").drop(columns="preventable").to_csv(tables / "sotif_instances.csv",
                                                                                index=False)
    error = render_blocks(tables)["readme-table"]
    assert str(error) == f"{tables / 'sotif_instances.csv'}: no column 'preventable'"


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
    text = readme.read_text()
    frames = re.search(r"\(21 presets x 2 drives, ([0-9,]+) frames", text).group(1)  # the sample's SOTIF frames
    readme.write_text(text.replace(f"{frames} frames", "492 frames", 1))
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
