import json

import numpy as np
import pandas as pd
import pytest

from harness import groups, rain, tables
from harness.core.kitti import KittiError

WEATHERS = ["ClearNoon", "WetNoon", "HardRainNoon", "ClearSunset", "CloudyNight", "SoftRainNight"]
BINS = ("0-30", "30-50", "50-80")
CLEAN = ("ClearNoon", "ClearSunset")


def _kitti(rng):
    return {m: {"0.7": {k: {d: float(rng.uniform(0, 100)) for d in ("easy", "moderate", "hard")} for k in ("R11", "R40")}}
            for m in ("bbox", "bev", "3d", "aos")}


def _row(rng, n):
    ap = float(rng.uniform(5, 90))
    return {"n_frames": n, "n_car": 2 * n, "headline": {"3d": {"0.7": ap, "0.5": ap + 5}, "bev": {"0.7": ap + 3, "0.5": ap + 6}},
            "headline_ci95": {"3d": [ap - 4, ap + 4], "bev": [ap - 1, ap + 7]},
            "kitti_moderate": {"3d": ap / 2, "bev": ap / 3},
            "distance": {"3d": {"0.7": {b: float(rng.uniform(0, 100)) for b in BINS}}},
            "recall": {"rcnn": {"0.3": 0.9, "0.5": 0.8, "0.7": float(rng.uniform(0, 1))}}}


def fake_result(rng, two_stage=False):
    rows = {w: _row(rng, 3) for w in WEATHERS}
    tod = {t: _row(rng, 6) for t in ("Noon", "Sunset", "Night")}
    res = {"kitti": _kitti(rng), "n_gt_kitti": {"easy": 0, "moderate": 7, "hard": 60},
           "headline": {"3d": {"0.7": 50.0}}, "distance": {},
           "recall": {"rcnn": {"0.3": 0.9, "0.5": 0.7, "0.7": 0.4}},
           "groups": {"column": "weather", "rows": rows},
           "groups_by": {"weather": {"column": "weather", "rows": rows}, "time_of_day": {"column": "time_of_day", "rows": tod}}}
    if two_stage:
        res["recall"]["roi"] = {"0.3": 0.95, "0.5": 0.6, "0.7": 0.2}
    return res


def test_kitti_and_recall_tables():
    rng = np.random.default_rng(0)
    results = {"one": fake_result(rng), "two": fake_result(rng, two_stage=True)}
    ap = tables.kitti_ap_table(results)
    assert len(ap) == 2 * 4 and ap.columns[2:8].tolist() == [f"AP{n} {d}" for n in (11, 40) for d in ("easy", "moderate", "hard")]
    assert ap.columns[8:].tolist() == ["cars easy", "cars moderate", "cars hard"]
    for r in ap.itertuples(index=False):
        ref = results[r.model]["kitti"][r.metric]["0.7"]
        assert list(r[2:8]) == [ref[k][d] for k in ("R11", "R40") for d in ("easy", "moderate", "hard")]
        assert list(r[8:]) == [results[r.model]["n_gt_kitti"][d] for d in ("easy", "moderate", "hard")]
    rec = tables.recall_table(results)
    assert rec["model"].tolist() == ["two"]
    assert rec.iloc[0]["roi@0.5"] == pytest.approx(60.0) and rec.iloc[0]["rcnn@0.3"] == pytest.approx(90.0)


def test_group_table_and_matrix_keep_weather_order():
    rng = np.random.default_rng(1)
    results = {"a": fake_result(rng), "b": fake_result(rng)}
    long = groups.group_table(results, "weather")
    assert len(long) == 2 * len(WEATHERS)
    m = groups.headline_matrix(long)
    assert list(m.index) == WEATHERS and list(m.columns) == ["a", "b"]
    for w in WEATHERS:
        for name in ("a", "b"):
            r = results[name]["groups_by"]["weather"]["rows"][w]
            assert m.loc[w, name] == r["headline"]["3d"]["0.7"]
            rec = long[(long.weather == w) & (long.model == name)].iloc[0]
            assert rec["ap3d_lo"] == r["headline_ci95"]["3d"][0]
            assert rec["ap3d_30-50m"] == r["distance"]["3d"]["0.7"]["30-50"]
            assert rec["recall@0.7"] == pytest.approx(100 * r["recall"]["rcnn"]["0.7"])
    wide = groups.headline_with_ci(long)
    assert wide.loc[wide.weather == "WetNoon", "b hi"].item() == results["b"]["groups"]["rows"]["WetNoon"]["headline_ci95"]["3d"][1]
    assert groups.group_table(results, "precipitation_class").empty


def test_robustness_against_plain_python():
    rng = np.random.default_rng(2)
    meta = pd.DataFrame({"weather": WEATHERS, "precipitation_class": ["dry", "wet", "rain", "dry", "dry", "rain"]})
    corrupt = ["WetNoon", "HardRainNoon", "SoftRainNight"]
    for _ in range(20):
        results = {name: fake_result(rng) for name in ("a", "b", "c")}
        for w in CLEAN:  # no clean AP for c: relative values undefined
            results["c"]["groups_by"]["weather"]["rows"][w]["headline"]["3d"]["0.7"] = 0.0
        aps = {n: {w: r["groups_by"]["weather"]["rows"][w]["headline"]["3d"]["0.7"] for w in WEATHERS}
               for n, r in results.items()}
        rob = rain.robustness_table(groups.group_table(results, "weather"), meta).set_index("model")
        for name in ("a", "b"):
            clean = (aps[name]["ClearNoon"] + aps[name]["ClearSunset"]) / 2
            assert rob.loc[name, "clean_ap3d"] == pytest.approx(clean)
            assert rob.loc[name, "mRR"] == pytest.approx(sum(aps[name][w] / clean for w in corrupt) / 3)
            assert rob.loc[name, "mRR_lo"] < rob.loc[name, "mRR"] < rob.loc[name, "mRR_hi"]
            assert rob.loc[name, "worst_preset"] == min(corrupt, key=lambda w: aps[name][w])  # never a clean preset
            lo, hi = rob.loc[name, ["mRR_lo", "mRR_hi"]]
            assert rob.loc[name, "reading"] == ("measurable loss" if hi < 1 else "measurable gain" if lo > 1
                                                else "no measurable loss")
        assert np.isnan(rob.loc["c", "mRR"])


def test_ratio_interval_against_monte_carlo():
    rng = np.random.default_rng(3)
    for _ in range(10):
        a, c = rng.uniform(40, 90, 2)
        s_a, s_c = rng.uniform(0.5, 3.0, 2)
        r, lo, hi = rain.ratio_interval(a, s_a, c, s_c)
        draws = rng.normal(a, s_a, 400_000) / rng.normal(c, s_c, 400_000)
        assert r == pytest.approx(a / c)
        assert (hi - lo) / (2 * rain.Z95) == pytest.approx(draws.std(), rel=0.03)
    assert np.isnan(rain.ratio_interval(1.0, 0.1, 0.0, 0.1)[0])
    assert rain.reading(0.95, 1.21) == "no measurable loss" and rain.reading(0.7, 0.9) == "measurable loss"


def _rain_result(rng):
    res = fake_result(rng)
    for rows in (res["groups_by"]["weather"]["rows"],):
        for w in ("SoftRainNoon", "MidRainyNoon"):
            rows[w] = _row(rng, 3)
    res["groups_by"]["precipitation_class"] = {"column": "precipitation_class",
                                               "rows": {c: _row(rng, 5) for c in ("dry", "wet", "rain")}}
    for rows in (res["groups_by"]["weather"]["rows"], res["groups_by"]["precipitation_class"]["rows"]):
        for row in rows.values():
            ap = row["headline"]["3d"]["0.5"]
            row["headline_ci95_0.5"] = {"3d": [ap - 2, ap + 1]}
    return res


def test_rain_story_reads_the_groups_at_both_ious():
    rng = np.random.default_rng(4)
    results = {"a": _rain_result(rng), "b": _rain_result(rng)}
    long = rain.rain_long(results)
    assert set(long["condition"]) == {"dry", "wet", "rain", "soft rain", "mid rain", "hard rain"}
    for r in long.itertuples():
        by = "precipitation_class" if r.condition in rain.PRECIPITATION else "weather"
        row = results[r.model]["groups_by"][by]["rows"][r.group]
        ci = row["headline_ci95"]["3d"] if r.iou == "0.7" else row["headline_ci95_0.5"]["3d"]
        assert (r.ap, r.ap_lo, r.ap_hi, r.n_car) == (row["headline"]["3d"][r.iou], ci[0], ci[1], row["n_car"])
    wide = rain.rain_display(long)
    assert wide[["model", "IoU"]].values.tolist() == [["a", "0.5"], ["b", "0.5"], ["a", "0.7"], ["b", "0.7"]]
    row = results["b"]["groups_by"]["precipitation_class"]["rows"]["rain"]
    ap = row["headline"]["3d"]["0.5"]
    assert wide.loc[1, "rain"] == f"{ap:.1f} [{ap - 2:.1f}, {ap + 1:.1f}]"
    assert list(wide.columns) == ["model", "IoU", "dry", "wet", "rain", "soft rain", "mid rain", "hard rain"]
    old = _rain_result(rng)  # a results file evaluated before the interval at IoU 0.5 was recorded
    del old["groups_by"]["weather"]["rows"]["HardRainNoon"]["headline_ci95_0.5"]
    hard = rain.rain_long({"a": old}).query("condition == 'hard rain'").set_index("iou")
    assert np.isnan(hard.loc["0.5", "ap_lo"]) and not hard[["ap"]].isna().any().item()
    assert not hard.loc["0.7", ["ap_lo", "ap_hi"]].isna().any()
    ap = hard.loc["0.5", "ap"]
    assert rain.rain_display(rain.rain_long({"a": old})).loc[0, "hard rain"] == f"{ap:.1f}"


def _preset_meta():
    from simulator import weather as sw
    rows = [{"weather": n, "time_of_day": sw.time_of_day(p), "rain_rate_mmh": sw.rain_rate_mmh(p),
             "precipitation": p.precipitation, "precipitation_deposits": p.precipitation_deposits,
             "wetness": p.wetness, "cloudiness": p.cloudiness, "precipitation_class": sw.precipitation_class(p)}
            for n, p in sw.WEATHER_PRESETS.items()]
    return pd.DataFrame(rows), sw


def test_presets_ordered_by_time_of_day_then_rain_rate():
    meta, sw = _preset_meta()
    order = rain.preset_order(list(reversed(meta["weather"])) + ["Unknown"], meta)
    assert order[-1] == "Unknown" and sorted(order[:-1]) == sorted(meta["weather"])
    key = [(("Noon", "Sunset", "Night").index(sw.time_of_day(sw.WEATHER_PRESETS[w])),
            sw.rain_rate_mmh(sw.WEATHER_PRESETS[w]), sw.road_water_cover(sw.WEATHER_PRESETS[w])) for w in order[:-1]]
    assert key == sorted(key)
    assert order[:2] == ["ClearNoon", "CloudyNoon"] and order[6] == "HardRainNoon"
    assert rain.clear_of_time(meta) == {"Noon": "ClearNoon", "Sunset": "ClearSunset", "Night": "ClearNight"}
    groups = rain.time_groups(order[:-1], meta)
    assert [(t, b, e) for t, b, e in groups] == [("Noon", 0, 7), ("Sunset", 7, 14), ("Night", 14, 21)]


def test_clear_delta_against_plain_python():
    meta, sw = _preset_meta()
    rng = np.random.default_rng(5)
    matrix = pd.DataFrame(rng.uniform(0, 100, (21, 2)), index=meta["weather"], columns=["a", "b"])
    delta = rain.clear_delta(matrix.drop(index="ClearNight"), meta)
    for w in delta.index:
        t = sw.time_of_day(sw.WEATHER_PRESETS[w])
        for m in ("a", "b"):
            if t == "Night":
                assert np.isnan(delta.loc[w, m])  # its clear preset is not in the matrix
            else:
                assert delta.loc[w, m] == pytest.approx(matrix.loc[w, m] - matrix.loc[f"Clear{t}", m])


def test_lidar_twins_share_rain_rate_and_road_water():
    meta, sw = _preset_meta()
    groups = rain.lidar_twins(meta)
    assert sorted(w for g in groups for w in g) == sorted(meta["weather"])
    for g in groups:
        keys = {(sw.rain_rate_mmh(sw.WEATHER_PRESETS[w]), sw.road_water_cover(sw.WEATHER_PRESETS[w])) for w in g}
        assert len(keys) == 1
    assert len({(sw.rain_rate_mmh(p), sw.road_water_cover(p)) for p in sw.WEATHER_PRESETS.values()}) == len(groups)
    assert ["ClearNoon", "CloudyNoon", "ClearSunset", "CloudySunset", "ClearNight", "CloudyNight"] in groups
    assert rain.lidar_twins(None) == []


def test_corrupt_presets_follow_meta():
    meta = pd.DataFrame({"weather": ["ClearNoon", "WetNoon", "CloudyNight"], "precipitation_class": ["dry", "dry", "rain"]})
    assert groups.corrupt_presets(["ClearNoon", "WetNoon", "CloudyNight"], meta) == ["CloudyNight"]
    assert groups.corrupt_presets(["ClearNoon", "WetNoon", "MidRainyNoon"], None) == ["WetNoon", "MidRainyNoon"]


def _summary(sotif=True, openvino=False):
    m = {"architecture": "x", "two_stage": False, "size_mb": 2.5, "params": 1_500_000, "results": "results/a.json",
         "train": {"seconds": 10.0},
         "runtime": {"onnxruntime": {"latency_ms_p50": 12.0, "latency_ms_p90": 15.0, "fps": 80.0},
                     "torch_eager_ms_p50": 30.0, "ort_speedup": 2.5, "peak_memory_mb": 300.0,
                     "agreement": {"same_boxes": 1.0, "max_abs_score_diff": 1e-6}}}
    if openvino:
        m["runtime"]["openvino"] = {"latency_ms_p50": 9.0, "agreement": {"same_boxes": 0.5}}
    if sotif:
        m["sotif"] = {"ClearNoon": {"threshold": 0.4, "detected": True, "distance_m": 55.0, "time_after_lane_change_s": 0.5,
                                    "distance_if_no_braking_m": 52.13,
                                    "stopping_distance_m": 19.0, "pass": True},
                      "HardRainNight": {"threshold": 0.4, "detected": False, "distance_m": None,
                                        "time_after_lane_change_s": None, "stopping_distance_m": 19.0, "pass": False},
                      "WetNoon": {"threshold": 0.4, "detected": False, "pass": None}}
    return {"schema": tables.RUN_SCHEMA, "models": {"a": m}}


def test_sotif_and_runtime_tables():
    s = _summary(openvino=True)
    long = tables.sotif_table(s)
    assert long["verdict"].tolist() == ["pass", "FAIL", "n/a"]
    assert tables.sotif_table(s, order=["WetNoon", "ClearNoon"])["weather"].tolist() == ["WetNoon", "ClearNoon", "HardRainNight"]
    wide = tables.sotif_matrix(long).set_index("weather")
    assert wide.loc["ClearNoon", "a"] == "pass 52.1 m vs 19.0 m, 0.5 s"
    assert wide.loc["HardRainNight", "a"] == "FAIL never (19.0 m)"
    assert wide.loc["WetNoon", "a"] == "n/a"
    rt = tables.runtime_table(s).iloc[0]
    assert rt["ort_p50_ms"] == 12.0 and rt["params_m"] == pytest.approx(1.5) and rt["ov_p50_ms"] == 9.0
    plain = tables.runtime_table(_summary(sotif=False))
    assert "ov_p50_ms" not in plain.columns and tables.sotif_table(_summary(sotif=False)).empty


def test_data_table_against_plain_aggregation():
    rng = np.random.default_rng(4)
    n = 40
    meta = pd.DataFrame({"frame_id": [f"{i:06d}" for i in range(n)], "weather": rng.choice(WEATHERS[:3], n),
                         "split": rng.choice(["test", "val"], n), "n_points": rng.integers(100, 1000, n)})
    stats = meta[["frame_id", "split", "weather"]].assign(mean_range_m=rng.uniform(10, 40, n))
    df = tables.data_table(meta, stats).set_index("weather")
    for w in set(meta.weather):
        sub = meta[meta.weather == w]
        assert df.loc[w, "n_frames"] == len(sub) and df.loc[w, "n_val"] == (sub.split == "val").sum()
        assert df.loc[w, "n_points_max"] == sub.n_points.max()
        assert df.loc[w, "n_points_mean"] == pytest.approx(sub.n_points.mean())
        assert df.loc[w, "mean_range_m_mean"] == pytest.approx(stats[stats.weather == w].mean_range_m.mean())
    assert tables.data_table(None, None).empty


def test_markdown_cells():
    df = pd.DataFrame({"name": ["a|b", "c"], "v": [1.23456, np.nan], "ok": [True, False]})
    md = tables.to_markdown(df, digits=1).splitlines()
    assert md[0] == "| name | v | ok |" and md[1] == "|---|---:|---|" and md[2] == "| a\\|b | 1.2 | yes |" and md[3] == "| c | – | no |"
    assert tables.fmt_float(3e-6, 2) == "3.0e-06" and tables.fmt_float(0.0, 2) == "0.00" and tables.fmt_float(0.006, 2) == "0.01"
    assert tables.to_markdown(pd.DataFrame()) == "_(no data)_\n"


def test_load_run_errors_name_the_file(tmp_path):
    with pytest.raises(KittiError, match="results.json: file not found"):
        tables.load_run(tmp_path)
    (tmp_path / "results.json").write_text("{not json")
    with pytest.raises(KittiError, match="results.json: not valid JSON"):
        tables.load_run(tmp_path)
    (tmp_path / "results.json").write_text(json.dumps({"schema": "other"}))
    with pytest.raises(KittiError, match="schema"):
        tables.load_run(tmp_path)
    (tmp_path / "results.json").write_text(json.dumps(_summary()))
    with pytest.raises(KittiError, match=r"results[/\\]a.json: file not found"):
        tables.load_run(tmp_path)
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "a.json").write_text(json.dumps({"kitti": {}}))
    with pytest.raises(KittiError, match="a.json: no 'headline'"):
        tables.load_run(tmp_path)


def test_write_tables_writes_three_formats(tmp_path):
    rng = np.random.default_rng(5)
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "a.json").write_text(json.dumps(fake_result(rng)))
    (tmp_path / "results.json").write_text(json.dumps(_summary()))
    out = tables.write_tables(tmp_path)
    for name in ("kitti_ap", "weather_headline", "robustness", "sotif", "runtime"):
        csv = pd.read_csv(tmp_path / "tables" / f"{name}.csv")
        assert len(csv) == len(out[name])
        assert len(json.loads((tmp_path / "tables" / f"{name}.json").read_text())) == len(out[name])
        assert (tmp_path / "tables" / f"{name}.md").read_text().startswith("|")
    assert not list((tmp_path / "tables").glob(".*.tmp"))
    ov = out["overview"].iloc[0]
    assert ov["AP3D"] == 50.0 and ov["SOTIF pass"] == "1/2" and ov["ORT p50 ms"] == 12.0 and ov["stages"] == "one"
    assert ov["mRR"] == pytest.approx(out["robustness"].iloc[0]["mRR"])


def test_fidelity_table_compares_each_weather_with_clear_noon_on_the_same_steps():
    from harness.tables import fidelity_table

    meta = pd.DataFrame({
        "weather": ["ClearNoon"] * 3 + ["HardRainNoon"] * 2,
        "scenario_time_s": [0.0, 3.0, 6.0, 3.0, 6.0],
        "slow_car_returns": [50, 20, 30, 18, 24],
        "slow_car_smeared": [0, 1, 0, 2, 1],
        "slow_car_range_m": [40.0, 50.0, 90.0, 50.0, 60.0],  # the 90 m frame is out of range
        "slow_car_t2": [1.0, 1.0, 1.0, 0.6, 0.64],
        "air_returns": [0, 2, 1, 7000, 7100],
    })
    t = fidelity_table(meta).set_index("weather")
    assert t.loc["ClearNoon", "n_frames"] == 2 and t.loc["ClearNoon", "car_returns_vs_clear"] == 1.0
    assert t.loc["HardRainNoon", "car_returns_vs_clear"] == pytest.approx(18 / 20)  # the steps both have
    assert t.loc["HardRainNoon", "predicted_T2"] == pytest.approx(0.62)
    assert t.loc["HardRainNoon", "smeared_per_car_return"] == pytest.approx(3 / 42)
    assert t.loc["ClearNoon", "air_returns"] == pytest.approx(1.0)  # over every frame of the preset
    assert fidelity_table(meta.drop(columns="air_returns")).empty


def test_the_papers_rows_stand_beside_ours():
    ap = {kind: {d: 50.0 for d in ("easy", "moderate", "hard")} for kind in ("R11", "R40")}
    res = {"second": {"kitti": {"3d": {"0.7": ap}}, "recall": {}},
           "parta2": {"kitti": {"bev": {"0.7": ap}},
                      "recall": {s: {t: 0.5 for t in ("0.3", "0.5", "0.7")} for s in ("roi", "rcnn")}}}
    t = tables.kitti_ap_table(res)
    paper = t[t["metric"] == tables.PAPER].set_index("model")
    assert paper.loc["second", "AP40 moderate"] == 81.42 and paper.loc["parta2", "AP11 easy"] == 85.59
    assert len(t) == 4  # one row of ours and the paper's per model
    rec = tables.recall_table(res).set_index("model")
    assert rec.loc[f"second: {tables.PAPER}", "roi@0.5"] == pytest.approx(36.9)
    assert rec.loc["parta2", "rcnn@0.3"] == 50.0 and np.isnan(rec.loc[f"second: {tables.PAPER}", "roi@0.7"])


def test_the_cap_is_what_a_perfect_detector_scores_over_n_cars():
    from harness.cells import binds, cap
    from harness.eval_kitti import Filter, build_eval_set, kitti_ap
    from harness.core.kitti import Labels
    for n in (1, 2, 5, 17, 40, 41, 45):
        xs = np.arange(n) * 6.0  # cars 6 m apart, each found exactly
        gt = Labels(name=np.array(["Car"] * n, dtype=object), truncated=np.zeros(n), occluded=np.zeros(n, int),
                    alpha=np.zeros(n), bbox=np.tile([100.0, 150, 200, 250], (n, 1)), dimensions=np.tile([1.5, 1.6, 3.9], (n, 1)),
                    location=np.c_[xs, np.full(n, 1.6), np.full(n, 20.0)], rotation_y=np.zeros(n))
        dt = Labels(**{**gt.__dict__, "score": np.linspace(0.9, 0.1, n)})
        ap = kitti_ap(build_eval_set([gt], [dt]), filters=(Filter("all"),))["3d"]["0.7"]
        assert cap(n, "R40") == pytest.approx(ap["R40"]["all"]) == pytest.approx(100 * min(n - 1, 40) / 40)
        assert cap(n, "R11") == pytest.approx(ap["R11"]["all"]) == pytest.approx(100 * np.ceil(min(n, 41) / 4) / 11)
        assert binds(n) == (n <= 40) == binds(n, "R11")
    assert cap(0) == 0.0 and binds(0)


def test_capped_and_empty_cells_read_as_such():
    from harness.cells import mark_capped
    df = pd.DataFrame({"model": ["a", "b", "c", "d"], "ap3d_0-30m": [0.0, 2.5, 63.25, 12.0],
                       "n_gt_0-30m": [0, 2, 50, np.nan], "ap3d": [1.0, 2.0, 3.0, 4.0]})
    out = mark_capped(df, 1)
    assert out["ap3d_0-30m"].tolist() == ["n/a (0 cars)", "2.5 (≤ 2.5)", 63.25, 12.0]
    assert out["ap3d"].tolist() == [1.0, 2.0, 3.0, 4.0]  # no count column beside it: as it was
    assert df["ap3d_0-30m"].tolist() == [0.0, 2.5, 63.25, 12.0]  # the input is left alone
    md = tables.to_markdown(mark_capped(tables.kitti_ap_table({"m": fake_result(np.random.default_rng(3))}), 2))
    assert md.count("n/a (0 cars)") == 2 * 4 and md.count("(≤ ") == 2 * 4  # easy: no car; moderate: 7 cars


def test_files_hold_rounded_numbers_and_counts_beside_the_aps(tmp_path):
    import re
    from harness.cells import round_floats
    assert round_floats(pd.DataFrame({"v": [34.599999999999994, 7.6e-06, 0.000123456, np.nan, 0.0, 1234.56789]}))[
        "v"].tolist()[:3] == [34.6, 7.6e-06, 0.00012]
    rng = np.random.default_rng(6)
    res = fake_result(rng)
    for row in res["groups_by"]["weather"]["rows"].values():
        row["headline"]["3d"]["0.7"] = 34.599999999999994
        row["headline_ci95"]["3d"] = [1 / 3, 2 / 3]
        row["n_gt"] = {"0-30": 0, "30-50": 2, "50-80": 45}
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "a.json").write_text(json.dumps(res))
    (tmp_path / "results.json").write_text(json.dumps(_summary()))
    tables.write_tables(tmp_path)
    for csv in (tmp_path / "tables").glob("*.csv"):
        assert not re.search(r"\d\.\d{7,}", csv.read_text()), csv.name
    detail = pd.read_csv(tmp_path / "tables" / "weather_detail.csv")
    assert (detail["ap3d"] == 34.6).all() and (detail["ap3d_lo"] == 0.3333).all()
    assert (detail["n_gt_0-30m"] == 0).all() and pd.api.types.is_float_dtype(detail["ap3d_0-30m"])  # numbers + counts
    md = (tmp_path / "tables" / "weather_detail.md").read_text()
    assert md.count("n/a (0 cars)") == len(WEATHERS) and md.count("(≤ 2.50)") == len(WEATHERS)
