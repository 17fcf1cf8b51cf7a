"""The boundary stage of a run: rounds of probes, the table, a real round on a simulated probe."""
import math
from dataclasses import replace

import pandas as pd

from harness import run_boundaries as rb
from harness.run import PROFILES, RunConfig
from harness.stages import Stages
from simulator.bounds import Probe
from tests.harness.conftest import centroid_detector

TINY = RunConfig("test", "tiny", train_frames=6, sotif_frames=21, epochs=1, workers=1, bootstrap=5, runtime_frames=2,
                 jobs=1)
LIMITS = {"A": 37.0, "B": 81.0}  # mm/h of rain each model passes up to (a_req 3 below, 9 above)


def fake_round(calls, unpreventable=()):
    def _round(stages, cfg, run_dir, r, probes, models, runtime, threads):
        calls.append((r, probes))
        return {p: {m: {"a_req": 3.0 if p.value <= LIMITS[m] else 9.0, "preventable": p.scenario not in unpreventable,
                        "reason": "occlusion"} for m in models} for p in probes}
    return _round


def test_profiles_name_their_plans():
    assert PROFILES["quick"].bounds == "quick" and PROFILES["default"].bounds == "default"
    assert TINY.bounds is None
    quick = rb.PLANS["quick"]
    assert len(quick.scenarios) * len(quick.axes) * quick.grid == 2 and quick.max_rounds == 0


def test_rounds_table_and_shared_reference_probe(tmp_path, monkeypatch):
    """Rain and water on two scenarios, the second unpreventable. Round 0: each scenario's grid, rain 0 and
    water 0 probed once (the reference itself): 2 x (3 + 3 - 1) = 10 probes."""
    calls = []
    monkeypatch.setattr(rb, "_round", fake_round(calls, unpreventable=("120-60_suv_black",)))
    plan = rb.BoundsPlan(("90-60_sedan_silver", "120-60_suv_black"), ("rain", "water"), seeds=(0, 1))
    path = rb.search_boundaries(Stages(tmp_path, False), TINY, tmp_path, {"A": 0.5, "B": 0.5}, "onnxruntime",
                                plan=plan)
    assert [r for r, _ in calls] == list(range(len(calls)))
    assert len(calls[0][1]) == 10 and Probe("90-60_sedan_silver", "water", 0.0) not in calls[0][1]
    all_probes = [p for _, ps in calls for p in ps]
    assert len(all_probes) == len(set(all_probes))
    df = pd.read_csv(path)
    assert tuple(df.columns) == rb.COLUMNS and len(df) == 2 * 2 * 2
    rain = df[(df["axis"] == "rain") & (df["scenario"] == "90-60_sedan_silver")].set_index("model")
    assert (rain.loc["A", "lo"], rain.loc["A", "hi"], rain.loc["B", "lo"], rain.loc["B", "hi"]) == (31.25, 37.5, 75, 81.25)
    assert set(rain["status"]) == {"bracketed"} and set(rain["unit"]) == {"mm/h"}
    water = df[(df["axis"] == "water") & (df["scenario"] == "90-60_sedan_silver")]
    assert set(water["status"]) == {"passes everywhere"}  # water is 0-1: every value <= 37
    assert set(df[df["scenario"] == "120-60_suv_black"]["status"]) == {"unpreventable (occlusion)"}


def test_a_real_round_simulates_predicts_and_judges_and_then_is_skipped(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "models").mkdir(parents=True)
    centroid_detector(run_dir / "models" / "centroid.onnx")
    cfg = replace(TINY, seed=1)
    probe = Probe("120-60_sedan_silver", "fog", 300.0)
    stages = Stages(run_dir, False)
    got = rb._round(stages, cfg, run_dir, 0, [probe], {"centroid": 0.5}, "onnxruntime", 1)
    v = got[probe]["centroid"]
    assert set(v) == {"a_req", "preventable", "reason"}
    assert v["preventable"] is False or math.isinf(v["a_req"])  # a box at the points' centroid is no hit
    meta = pd.read_csv(run_dir / "data" / "bounds" / "r0" / "meta" / "frames.csv")
    assert set(meta["reference_scenario"]) == {probe.scenario} and set(meta["axis_value"]) == {300.0}
    assert (run_dir / "predictions_bounds" / "r0" / "centroid").is_dir()
    records = {p.stem: p.stat().st_mtime_ns for p in (run_dir / ".stages").glob("*.json")}
    assert set(records) == {"simulate_bounds_r0", "predict_bounds_r0_centroid", "verdict_bounds_r0"}
    assert rb._round(stages, cfg, run_dir, 0, [probe], {"centroid": 0.5}, "onnxruntime", 1) == got
    assert {p.stem: p.stat().st_mtime_ns for p in (run_dir / ".stages").glob("*.json")} == records


def test_no_plan_no_stage(tmp_path):
    rb.boundaries_stage(Stages(tmp_path, False), TINY, tmp_path, {}, "onnxruntime")
    assert not (tmp_path / rb.TABLE).exists()
