import json

import numpy as np
import pandas as pd
import pytest

from harness import report, report_space
from harness.core.files import atomic_write_text
from harness.run_space import latency_s, space_summary
from tests.harness.test_report import make_run


def synthetic_view(rng, n=12):
    """A scenario-space view as ``instance_view`` writes it: n instances, 5 slow-car frames each."""
    rain = rng.uniform(0, 80, n)
    margin = 30.0 - rain  # wetter, later: fails above 30 mm/h
    instances = [{"instance_key": f"Sweep#{i}", "weather": "Sweep", "instance": i, "sweep_axis": "rain",
                  "rain_rate_mmh": float(rain[i]), "fog_mor_m": 0.0, "sc_slow_reflectance": 0.05 + 0.05 * (i % 6),
                  "precipitation_class": "rain" if rain[i] > 1 else "dry", "n_frames": 5, "detected": True,
                  "confirmed": i % 4 != 3, "margin_m": float(margin[i]) if i % 4 != 3 else None,
                  "pass": bool(margin[i] >= 0 and i % 4 != 3)} for i in range(n)]
    keys = np.repeat([r["instance_key"] for r in instances], 5)
    frames = {"instance_key": keys.tolist(), "distance_m": rng.uniform(20, 80, 5 * n).tolist(),
              "hit": (rng.uniform(size=5 * n) < 0.6).tolist(),
              "rain_rate_mmh": np.repeat(rain, 5).tolist(), "fog_mor_m": [0.0] * (5 * n),
              "sc_slow_reflectance": np.repeat([r["sc_slow_reflectance"] for r in instances], 5).tolist()}
    return {"rule": {"k": 3, "n": 5, "latency_s": 0.04, "threshold": 0.5}, "instances": instances, "frames": frames}


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


def test_latency_in_seconds():
    assert latency_s({"onnxruntime": {"latency_ms_p50": 40.0}}) == 0.04 and latency_s({}) == 0.0


def test_space_summary_of_a_data_set_without_instances(space_run):
    _, doc = space_run
    view = doc["models"]["alpha"]["sotif_space"]["sotif"]
    assert [r["instance_key"] for r in view["instances"]] == ["ClearNoon", "ClearSunset", "HardRainNight"]
    assert view["rule"]["latency_s"] == pytest.approx(0.04)
    cal = doc["models"]["alpha"]["calibration"]
    assert set(cal["0.7"]) == {"all", "dry", "rain"} and cal["0.7"]["all"]["n"] == 27  # 3 boxes x 9 test frames


def test_tables_and_section(space_run):
    root, doc = space_run
    rates = pd.read_csv(root / "tables" / "sotif_pass_rates.csv")
    sweep = rates[(rates.model == "alpha") & (rates.set == "sweep")]
    inst = pd.DataFrame(doc["models"]["alpha"]["sotif_space"]["sweep"]["instances"])
    row = sweep[sweep.column == "weather"].iloc[0]
    assert row["n"] == 12 and row["n_pass"] == inst["pass"].sum() and not row["too_few"]
    assert (sweep[sweep.column == "rain_rate_mmh"]["n"] == 6).all()  # 12 values: two bins of >= 5 instances
    trig = pd.read_csv(root / "tables" / "triggering_conditions.csv")
    assert len(trig[trig.model == "alpha"]) == report_space.N_TRIGGERING and "weather" not in set(trig["column"])
    judged = trig[(trig.model == "alpha") & ~trig.too_few]
    assert judged["rate"].is_monotonic_increasing
    boundary = pd.read_csv(root / "tables" / "sotif_boundary.csv")
    rain = boundary[(boundary.model == "alpha") & (boundary["map"] == "rain")]
    frames = pd.concat([pd.DataFrame(doc["models"]["alpha"]["sotif_space"][k]["frames"]) for k in ("sotif", "sweep")])
    assert rain["n"].sum() == frames["rain_rate_mmh"].notna().sum() >= 60  # every slow-car frame with a rain rate
    assert rain.loc[rain.n == 0, "p_detect"].isna().all()
    for name in ("sotif_instances", "calibration"):
        assert (root / "tables" / f"{name}.csv").is_file()
    md = (root / "report.md").read_text()
    assert "## SOTIF over the scenario space" in md and "holding 3 hits" in md and "Wilson" in md
    assert "sweep: 12 instances" in md and "bootstrap over frames" in md
    lead = md.index("## Where each detector stops finding the slow car in time")
    assert lead < md.index("## Models at a glance") < md.index("## SOTIF over the scenario space")
    assert "| sweep | all instances |" in md[lead:md.index("## Models at a glance")]
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
