import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness import report, report_bounds, report_space, run_boundaries
from harness.core.files import atomic_write_text
from harness.core.kitti import KittiError
from harness.run_space import latency_ms, space_summary
from tests.harness.test_report import make_run


def synthetic_view(rng, n=12):
    """A scenario-space verdict as ``harness.verdict.verdict`` writes it: n instances (every 4th a van), their
    perception and system rows, 5 frames each."""
    rain = rng.uniform(0, 80, n)
    margin = 30.0 - rain  # wetter, later: fails above 30 mm/h
    rows = []
    for i in range(n):
        body = "van" if i % 4 == 3 else "sedan"
        base = {"instance": f"Sweep#{i}", "weather": "Sweep", "sweep_axis": "rain", "rain_mm_h": float(rain[i]),
                "fog_mor_m": 0.0, "water": 0.0, "reflectance": 0.05 + 0.05 * (i % 6), "paint": "silver",
                "body": body, "body_class": "car" if body == "sedan" else "outside the learned classes",
                "precipitation_class": "rain" if rain[i] > 1 else "dry", "n_frames": 5,
                "preventable": i % 6 != 5, "reason": None if i % 6 != 5 else "occlusion", "reference_confirm_s": 0.4}
        for kind, late in (("perception", 0.0), ("system", 10.0)):
            m = float(margin[i] - late)
            rows.append({**base, "verdict": kind, "model": "x", "confirm_s": 0.6, "delay_s": 0.2, "margin_m": m,
                         "a_req_mps2": 3.0 if m >= 0 else 7.0, "passed": bool(m >= 0)})
    keys = np.repeat([f"Sweep#{i}" for i in range(n)], 5)
    frames = {"instance": keys.tolist(), "distance_m": rng.uniform(20, 80, 5 * n).tolist(),
              "hit": (rng.uniform(size=5 * n) < 0.6).tolist(),
              "rain_rate_mmh": np.repeat(rain, 5).tolist(), "fog_mor_m": [0.0] * (5 * n),
              "sc_slow_reflectance": np.repeat([0.05 + 0.05 * (i % 6) for i in range(n)], 5).tolist()}
    phantoms = [{"weather": "Sweep: rain", "n_frames": 5 * n, "hours": 5 * n * 0.1 / 3600, "n_false": 3,
                 "false_per_h": 3 / (5 * n * 0.1 / 3600), "n_events": 0, "events_per_h": 0.0}]
    return {"rule": {"k": 3, "window_s": 0.5, "reaction_s": 0.35}, "threshold": 0.5, "instances": rows,
            "phantoms": phantoms, "frames": frames}


@pytest.fixture(scope="module")
def space_run(tmp_path_factory):
    root = make_run(tmp_path_factory.mktemp("run"))
    doc = json.loads((root / "results.json").read_text())
    rng = np.random.default_rng(0)
    for name, m in doc["models"].items():
        m.update(space_summary(root, name, 0.5, m["runtime"]))  # the SOTIF set: one instance per weather
        m["sotif_space"]["sweep"] = synthetic_view(rng)
    atomic_write_text(root / "results.json", json.dumps(doc))
    report.render(root)
    return root, doc


def test_latency_is_the_p90_in_ms():
    assert latency_ms({"onnxruntime": {"latency_ms_p50": 40.0, "latency_ms_p90": 55.0}}) == 55.0
    assert latency_ms({}) is None


def test_space_summary_of_a_data_set_without_instances(space_run):
    _, doc = space_run
    view = doc["models"]["alpha"]["sotif_space"]["sotif"]
    rows = pd.DataFrame(view["instances"])
    assert list(dict.fromkeys(rows["instance"])) == ["ClearNoon", "ClearSunset", "HardRainNight"]
    assert set(rows["verdict"]) == {"perception", "system"} and (rows.loc[rows.verdict == "system", "latency_ms"] == 50.0).all()
    assert set(rows["body"]) == {"sedan"} and view["rule"]["reaction_s"] == 0.35
    cal = doc["models"]["alpha"]["calibration"]
    assert set(cal["0.7"]) == {"all", "dry", "rain"} and cal["0.7"]["all"]["n"] == 27  # 3 boxes x 9 test frames


def test_tables_and_section(space_run):
    root, doc = space_run
    rates = pd.read_csv(root / "tables" / "sotif_pass_rates.csv")
    sweep = rates[(rates.model == "alpha") & (rates.set == "sweep") & (rates.verdict == "perception")]
    inst = pd.DataFrame(doc["models"]["alpha"]["sotif_space"]["sweep"]["instances"]).query("verdict == 'perception'")
    car = inst[inst.body_class == "car"]
    row = sweep[(sweep.column == "all") & (sweep.body_class == "car")].iloc[0]
    assert row["n"] == car["preventable"].sum() == 8 and row["n_pass"] == (car["passed"] & car["preventable"]).sum()
    assert row["n_unpreventable"] == 1 and not row["too_few"]  # instance 5 (occlusion); 11 is a van
    vans = sweep[(sweep.column == "all") & (sweep.body_class == "outside the learned classes")].iloc[0]
    assert (vans["n"], vans["n_unpreventable"]) == (2, 1)  # instances 3, 7 and 11 (unpreventable)
    trig = pd.read_csv(root / "tables" / "triggering_conditions.csv")
    alpha = trig[trig.model == "alpha"]
    assert len(alpha) == report_space.N_TRIGGERING and not {"weather", "all"} & set(alpha["column"])
    assert alpha[~alpha.too_few]["rate"].is_monotonic_increasing
    boundary = pd.read_csv(root / "tables" / "sotif_boundary.csv")
    rain = boundary[(boundary.model == "alpha") & (boundary["map"] == "rain")]
    frames = pd.concat([pd.DataFrame(doc["models"]["alpha"]["sotif_space"][k]["frames"]) for k in ("sotif", "sweep")])
    assert rain["n"].sum() == frames["rain_rate_mmh"].notna().sum() >= 60  # every judged frame with a rain rate
    assert rain.loc[rain.n == 0, "p_detect"].isna().all()
    for name in ("sotif_instances", "sotif_phantoms", "calibration"):
        assert (root / "tables" / f"{name}.csv").is_file()
    table = pd.read_csv(root / "tables" / "sotif_instances.csv")
    assert {"preventable", "reason", "delay_s", "a_req_mps2", "verdict"} <= set(table.columns)
    md = (root / "report.md").read_text()
    assert "## SOTIF over the scenario space" in md and "in-path hit" in md and "Wilson" in md
    assert "sweep: 12 instances" in md and "bootstrap over frames" in md
    lead = md.index("## Where each detector stops finding the slow car in time")
    head = md[lead:md.index("## Models at a glance")]
    assert lead < md.index("## Models at a glance") < md.index("## SOTIF over the scenario space")
    assert "| sweep | car-bodied: all |" in head and "vans and trucks (outside the learned classes)" in head
    assert "system verdict" in head and "phantom in-path boxes per hour" in head
    assert "## SOTIF view: the slow car after the cut-out" not in md  # the one-frame view goes with the verdict
    matrix = report_space.rate_matrix(rates)
    assert matrix.columns.name is None and list(matrix.columns[:2]) == ["set", "condition"]
    for fig in ("sotif_margins", "boundary_alpha", "boundary_beta", "reliability"):
        assert (root / "figures" / f"{fig}.png").is_file() and f"figures/{fig}.png" in md


def test_a_run_without_scenario_space_writes_no_new_files(tmp_path):
    root = make_run(tmp_path)
    report.render(root)
    assert not (root / "tables" / "sotif_instances.csv").exists()
    assert "scenario space" not in (root / "report.md").read_text()


def test_an_interval_over_few_instances_says_so():
    rows = lambda m: {"a": {"groups_by": {"weather": {"rows": {"ClearNoon": {"ci_method": m}}}}}}
    few = report_space.ci_method(rows("bootstrap over instances (2 instances, 200 resamples)"))
    assert "spread of 2 drives, not a 95% interval" in few
    assert report_space.ci_method(rows("bootstrap over instances (6 instances, 200 resamples)")).endswith("resamples)")
    assert report_space.ci_method(rows("bootstrap over frames (200 resamples)")) == "bootstrap over frames (200 resamples)"


# ----------------------------------------------------------------------------- boundaries (harness.report_bounds)
WIDE = "bracketed wider than the tolerance (round limit)"
BOUNDS = pd.DataFrame([  # tables/sotif_boundaries.csv with every status of harness.boundaries
    ("alpha", "rain", "120-60_sedan_silver", 25.0, 50.0, "mm/h", WIDE, 3),
    ("beta", "rain", "120-60_sedan_silver", 0.0, 100.0, "mm/h", "passes everywhere", 3),
    ("alpha", "fog", "120-60_sedan_silver", 316.228, 1000.0, "m", WIDE, 4),
    ("beta", "fog", "120-60_sedan_silver", 900.0, 1000.0, "m", "bracketed", 4),
    ("alpha", "water", "120-60_suv_black", 0.0, 1.0, "share", "fails everywhere", 3),
    ("beta", "water", "120-60_suv_black", 0.25, 0.3, "share",
     "bracketed; not monotone (2 flips); seeds disagree at hi (1 of 3 pass)", 3),
    ("alpha", "reflectance", "120-60_suv_black", 0.02, 0.8, "reflectance", "unpreventable (occlusion)", 2),
    ("beta", "reflectance", "120-60_suv_black", 0.02, 0.8, "reflectance", "no verdict", 2),
    ("alpha", "reflectance", "120-60_sedan_silver", 0.41, 0.8, "reflectance", WIDE, 3),
], columns=["model", "axis", "scenario", "lo", "hi", "unit", "status", "n_probes"])
BOUND_ROWS = [  # condition, alpha's cell, beta's cell
    ("boundary: rain (mm/h), 120-60 sedan silver", "fails above 25-50 mm/h (bracket wider than ±5 mm/h)",
     "passes everywhere in 0-100 mm/h"),
    ("boundary: fog visibility (m), 120-60 sedan silver", "fails below 316-1,000 m (bracket wider than ±10 %)",
     "fails below 900-1,000 m"),
    ("boundary: road water (share of the road), 120-60 suv black", "fails everywhere in 0.00-1.00",
     "fails above 0.25-0.30; not monotone (2 flips); seeds disagree at hi (1 of 3 pass)"),
    ("boundary: slow car reflectance at 905 nm, 120-60 suv black", "unpreventable (occlusion)", "no verdict"),
    ("boundary: slow car reflectance at 905 nm, 120-60 sedan silver", "fails below 0.41-0.80 (bracket wider than "
     "±0.05)", None),
]


def _write_bounds(root, df=BOUNDS):
    atomic_write_text(root / run_boundaries.TABLE, df.to_csv(index=False, lineterminator="\n"))


def test_boundary_cells_say_where_each_model_fails(tmp_path):
    _write_bounds(tmp_path)
    bounds = report_bounds.read(tmp_path)
    pd.testing.assert_frame_equal(bounds, BOUNDS)
    rows = report_bounds.lead_rows(bounds)
    assert list(rows.columns) == ["set", "condition", "alpha", "beta"] and set(rows["set"]) == {"bounds"}
    assert [(r.condition, r.alpha, None if pd.isna(r.beta) else r.beta) for r in rows.itertuples()] == BOUND_ROWS
    shown = report_bounds.table(bounds)
    assert list(shown["lo"]) == ["25", "0", "316", "900", "0.00", "0.25", "0.02", "0.02", "0.41"]
    assert list(shown["hi"]) == ["50", "100", "1,000", "1,000", "1.00", "0.30", "0.80", "0.80", "0.80"]


def test_the_boundaries_caption_says_the_plan_and_the_tolerances():
    text = report_bounds.caption({"config": {"bounds": "quick"}})
    assert 'plan "quick": per reference scenario and axis its two ends, no refinement, noise seed 0' in text
    assert 'plan "default": per reference scenario and axis its two ends, then the midpoint of each bracket wider ' \
           "than the tolerance until all are within it, noise seed 0, the final brackets again with seeds 1, 2" in \
           report_bounds.caption({"config": {"bounds": "default"}})
    assert "±5 mm/h rain, ±10 % fog visibility, ±0.05 road water, ±0.05 reflectance" in text
    assert "3 values, ends included, then the midpoint of each bracket wider than the tolerance until all are " \
           "within it, noise seed 0, the final brackets again with seeds 1, 2" in report_bounds.caption(
               {"config": {"bounds": "tolerance"}})
    assert "(plan not recorded)" in report_bounds.caption({})


@pytest.mark.parametrize("content", ["", "model,axis,scenario,lo,hi,unit,status,n_probes\n"])
def test_an_empty_boundaries_table_adds_nothing(tmp_path, content):
    (tmp_path / "tables").mkdir()
    (tmp_path / run_boundaries.TABLE).write_text(content)
    assert report_bounds.read(tmp_path).empty and report_bounds.read(tmp_path / "none").empty
    matrix = pd.DataFrame({"set": ["sotif"], "condition": ["car-bodied: all"], "alpha": ["1/2"],
                           "unpreventable": ["0"]})
    assert report_bounds.with_rows(report_bounds.lead_rows(report_bounds.read(tmp_path)), matrix) is matrix


@pytest.mark.parametrize("content,message", [
    ('model,axis\n"x,1\n', "not a readable CSV table"),
    ("model,axis,lo\na,rain,1\n", "no scenario, hi, unit, status, n_probes columns"),
    ("model,axis,scenario,lo,hi,unit,status,n_probes\na,rain,s,1,x,mm/h,bracketed,3\n", "hi is not a number ('x')"),
    ("model,axis,scenario,lo,hi,unit,status,n_probes\na,rain,s,1,2,mm/h,,3\n", "empty status"),
])
def test_a_malformed_boundaries_table_names_the_file(tmp_path, content, message):
    (tmp_path / "tables").mkdir()
    (tmp_path / run_boundaries.TABLE).write_text(content)
    path = re.escape(str(tmp_path / run_boundaries.TABLE))
    with pytest.raises(KittiError, match=f"{path}(:2)?: {re.escape(message)}"):
        report_bounds.read(tmp_path)


@pytest.fixture(scope="module")
def bounded_run(space_run, tmp_path_factory):
    """The scenario-space run with a boundaries table and the default plan in its config, rendered."""
    root = Path(shutil.copytree(space_run[0], tmp_path_factory.mktemp("bounded") / "run"))
    _write_bounds(root)
    doc = json.loads((root / "results.json").read_text())
    atomic_write_text(root / "results.json", json.dumps({**doc, "config": {"bounds": "default"}}))
    report.render(root)
    return root


def test_boundary_rows_lead_the_answer_and_the_table_sits_in_the_space_section(bounded_run):
    root = bounded_run
    md = (root / "report.md").read_text()
    lead = md[md.index("## Where each detector stops finding the slow car in time"):md.index("## Models at a glance")]
    assert "The bounds rows come first" in lead
    body = [line for line in lead.splitlines() if line.startswith("| ")][1:]  # after the header
    assert body[:len(BOUND_ROWS)] == [f"| bounds | {c} | {a} | {b or '–'} | – |" for c, a, b in BOUND_ROWS]
    assert body[len(BOUND_ROWS)].startswith("| sotif | car-bodied: all |")
    space = md[md.index("## SOTIF over the scenario space"):]
    assert space.index('### Boundaries (plan "default"') < space.index("### Model pairs whose verdicts differ")
    assert "| alpha | fog | 120-60_sedan_silver | 316 | 1,000 | m | bracketed wider than the tolerance (round " \
           "limit) | 4 |" in space
    html = (root / "index.html").read_text()
    assert '<td class="fail">fails everywhere in 0.00-1.00</td>' in html
    assert '<td class="pass">passes everywhere in 0-100 mm/h</td>' in html
    assert pd.read_csv(root / run_boundaries.TABLE).equals(BOUNDS)  # the run's file is read, never rewritten


def test_a_run_without_boundaries_renders_as_before(space_run):
    md = (space_run[0] / "report.md").read_text()
    lead = md[md.index("## Where each detector stops finding the slow car in time"):md.index("## Models at a glance")]
    assert "| bounds |" not in md and "### Boundaries" not in md and "bounds rows" not in md
    assert [line for line in lead.splitlines() if line.startswith("| ")][1].startswith("| sotif | car-bodied: all |")


def test_the_reliability_figure_of_a_model_without_scored_detections_says_so(recwarn):
    """A calibration whose every score bin is empty (a model that detected nothing) draws no legend (matplotlib
    warns of one without artists) and says why the panel is empty."""
    empty = {"bins": {"confidence": [None] * 10, "accuracy": [None] * 10}, "ece": 0.0}
    scored = {"bins": {"confidence": [0.15, None, 0.85], "accuracy": [0.1, None, 0.9]}, "ece": 0.05}
    summary = {"models": {"a": {"calibration": {"0.7": {"dry": empty, "rain": empty}}},
                          "b": {"calibration": {"0.7": {"dry": scored}}}}}
    fig = report_space.reliability_figure(summary)
    a, b = fig.axes
    assert a.get_legend() is None and [t.get_text() for t in a.texts] == ["no scored detection"]
    assert [t.get_text() for t in b.get_legend().get_texts()] == ["dry (ECE 0.050)"] and not b.texts
    assert not [w for w in recwarn if "legend" in str(w.message)]
