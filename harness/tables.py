"""The tables of a benchmark run, built from its result files (pandas; CSV + JSON + Markdown).

Loader (``load_run``), pure functions from the loaded result dicts to DataFrames, and one driver
(``write_tables``) writing ``RUN/tables/<name>.{csv,json,md}``. AP values are in percent, recalls
are converted to percent, latencies in ms, sizes in MB. Rows follow the order in which the
evaluation met the groups (the data set's weather order).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from harness import provenance, rain, report_bounds, report_space, result_schema
from harness.cells import DIFFS, mark_capped, round_floats
from harness.core.files import atomic_write_text
from harness.core.kitti import KittiError, read_frames_meta
from harness.groups import group_rows, group_table, headline_matrix, headline_with_ci, relative_table
from harness.published_run import weights

RUN_SCHEMA = "sotif-bench/run/1"


@dataclass
class Run:
    """A run directory's result files, loaded."""

    run_dir: Path
    summary: dict  # results.json
    results: dict  # model name -> results/<name>.json
    meta: pd.DataFrame | None  # data/sotif/meta/frames.csv
    frame_stats: pd.DataFrame | None  # tables/data_stats.csv (per frame)
    boundaries: pd.DataFrame  # tables/sotif_boundaries.csv (harness.run_boundaries); empty when the run has none

    @property
    def models(self) -> list[str]:
        return list(self.summary["models"])


def read_json_object(path: Path) -> dict:
    """The JSON object in ``path``; a KittiError naming the file when it is missing, not JSON or not an object."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise KittiError(path, "file not found") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise KittiError(path, f"not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise KittiError(path, "expected a JSON object")
    return data


def _check_summary(path: Path, summary: dict) -> None:
    if summary.get("schema") != RUN_SCHEMA:
        raise KittiError(path, f"schema is {summary.get('schema')!r}, expected {RUN_SCHEMA!r}")
    models = summary.get("models")
    if not isinstance(models, dict) or not models:
        raise KittiError(path, "no models in the run summary")
    for name, m in models.items():
        if not isinstance(m, dict) or "results" not in m:
            raise KittiError(path, f"model {name!r} has no 'results' entry")
    result_schema.check(path, summary, result_schema.SUMMARY)


def load_run(run_dir) -> Run:
    """Load results.json, every model's results file, the data meta, the per-frame data statistics and the
    boundaries table; a JSON value of the wrong type raises ``KittiError`` naming the file and the key
    (``harness.result_schema``), a malformed boundaries table one naming the file (``report_bounds.read``)."""
    run_dir = Path(run_dir)
    path = run_dir / "results.json"
    summary = read_json_object(path)
    _check_summary(path, summary)
    results = {}
    for name, m in summary["models"].items():
        res_path = run_dir / m["results"]
        res = read_json_object(res_path)
        for key in ("kitti", "headline", "distance", "recall"):
            if key not in res:
                raise KittiError(res_path, f"no {key!r} entry (not a harness.evaluate results file)")
        result_schema.check(res_path, res, result_schema.RESULTS)
        results[name] = res
    meta_path, stats_path = run_dir / "data" / "sotif" / "meta" / "frames.csv", run_dir / "tables" / "data_stats.csv"
    meta = read_frames_meta(meta_path) if meta_path.is_file() else None
    stats = read_frames_meta(stats_path) if stats_path.is_file() else None
    return Run(run_dir, summary, results, meta, stats, report_bounds.read(run_dir))


# ----------------------------------------------------------------------------- paper tables
# Patel & Jung, VEHITS 2024: KITTI-pretrained models in MMDetection3D on its 547-frame CARLA set, Car at IoU 0.7,
# AP11 easy/moderate/hard then AP40 easy/moderate/hard; the paper does not say for which of bbox, BEV or 3D.
PAPER_AP = {
    "parta2": (85.59, 75.94, 75.42, 86.57, 77.87, 75.61), "pv_rcnn": (89.77, 88.09, 87.39, 89.80, 82.23, 79.54),
    "pointpillars": (86.20, 76.90, 74.07, 94.83, 90.99, 87.78), "mvx_net": (81.99, 70.91, 71.76, 82.89, 70.68, 70.35),
    "dv_second": (89.42, 87.82, 85.82, 93.23, 80.21, 70.87), "second": (87.00, 76.95, 74.84, 88.56, 81.42, 75.35),
}
# its OpenPCDet recall (fractions): RoI @0.3, RCNN @0.3, RoI @0.5, RCNN @0.5
PAPER_RECALL = {"parta2": (0.516, 0.515, 0.354, 0.346), "point_rcnn": (0.450, 0.460, 0.232, 0.288),
                "second": (0.515, 0.516, 0.369, 0.369)}
PAPER = "paper (weather-blind LiDAR)"


def kitti_ap_table(results: dict) -> pd.DataFrame:
    """The paper's AP table: per model and metric (bbox/BEV/3D/AOS), AP11 and AP40 at IoU 0.7 for
    easy/moderate/hard (columns ``AP11 easy`` ... ``AP40 hard``) and the Car boxes each difficulty
    counts (``cars easy`` ...; empty for results without them), and the paper's own row beside them."""
    cols = [f"AP{kind[1:]} {d}" for kind in ("R11", "R40") for d in DIFFS]
    rows = []
    for name, res in results.items():
        counts = {f"cars {d}": res.get("n_gt_kitti", {}).get(d, np.nan) for d in DIFFS}
        for metric in ("bbox", "bev", "3d", "aos"):
            if metric in res["kitti"]:
                v = res["kitti"][metric]["0.7"]
                rows.append({"model": name, "metric": metric,
                             **{f"AP{kind[1:]} {d}": v[kind][d] for kind in ("R11", "R40") for d in DIFFS}, **counts})
        if name in PAPER_AP:
            rows.append({"model": name, "metric": PAPER, **dict(zip(cols, PAPER_AP[name]))})
    return pd.DataFrame(rows, columns=["model", "metric", *cols, *(f"cars {d}" for d in DIFFS)])


def recall_table(results: dict) -> pd.DataFrame:
    """The paper's recall table (percent) for two-stage models: RoI and RCNN at IoU 0.3 / 0.5 / 0.7."""
    rows = []
    for name, res in results.items():
        rec = res["recall"]
        if "roi" not in rec:
            continue
        rows.append({"model": name, **{f"{stage}@{t}": 100.0 * rec[stage][t]
                                       for stage in ("roi", "rcnn") for t in ("0.3", "0.5", "0.7")}})
    for name in results:
        if name in PAPER_RECALL:
            paper = dict(zip(("roi@0.3", "rcnn@0.3", "roi@0.5", "rcnn@0.5"), 100.0 * np.array(PAPER_RECALL[name])))
            rows.append({"model": f"{name}: {PAPER}", **paper})
    return pd.DataFrame(rows, columns=["model", *[f"{s}@{t}" for s in ("roi", "rcnn") for t in ("0.3", "0.5", "0.7")]])


# ----------------------------------------------------------------------------- SOTIF, runtime, data
SOTIF_COLUMNS = ["weather", "model", "threshold", "detected", "time_after_lane_change_s", "distance_m",
                 "distance_at_lane_change_m", "closing_speed_mps", "distance_if_no_braking_m", "stopping_distance_m",
                 "verdict"]


def sotif_table(summary: dict, order=None) -> pd.DataFrame:
    """Long table: per (weather, model) the first detection of the slow car vs the stopping distance
    (``harness.sotif`` fields); weathers in ``order`` first (e.g. the data set's), then any others."""
    rows = []
    for name, m in summary["models"].items():
        for weather, r in (m.get("sotif") or {}).items():
            verdict = "n/a" if r.get("pass") is None else ("pass" if r["pass"] else "FAIL")
            rows.append({**{c: r.get(c) for c in SOTIF_COLUMNS}, "weather": weather, "model": name, "verdict": verdict})
    df = pd.DataFrame(rows, columns=SOTIF_COLUMNS)
    rank = {w: i for i, w in enumerate(dict.fromkeys([*(order or []), *df["weather"]]))}
    return df.sort_values("weather", key=lambda c: c.map(rank), kind="stable").reset_index(drop=True)


def sotif_matrix(long: pd.DataFrame) -> pd.DataFrame:
    """Weather x model cells: "pass 52.1 m vs 19.0 m, 0.5 s" (distance left at the detection without
    braking vs stopping distance, time after the lane change), "FAIL never (19.0 m)" or "n/a"."""
    if long.empty:
        return pd.DataFrame()

    def cell(r) -> str:
        if r["verdict"] == "n/a":
            return "n/a"
        if not r["detected"]:
            return f"{r['verdict']} never ({r['stopping_distance_m']:.1f} m)"
        return (f"{r['verdict']} {r['distance_if_no_braking_m']:.1f} m vs {r['stopping_distance_m']:.1f} m, "
                f"{r['time_after_lane_change_s']:.1f} s")
    wide = long.assign(cell=long.apply(cell, axis=1)).pivot(index="weather", columns="model", values="cell")
    wide = wide.reindex(index=list(dict.fromkeys(long["weather"])), columns=list(dict.fromkeys(long["model"])))
    wide.columns.name = None
    return wide.rename_axis("weather").reset_index()


def _get(d: dict, *keys, default=np.nan):
    for k in keys:
        if not isinstance(d, dict) or d.get(k) is None:
            return default
        d = d[k]
    return d


def runtime_table(summary: dict) -> pd.DataFrame:
    """Per model: ORT latency p50/p90, frames/s, size, parameters, peak memory, torch-vs-ORT agreement,
    and OpenVINO latency/agreement when the run has them."""
    rows = []
    for name, m in summary["models"].items():
        rt = m.get("runtime", {})
        row = {"model": name, "architecture": m.get("architecture"), "two_stage": m.get("two_stage"),
               "ort_p50_ms": _get(rt, "onnxruntime", "latency_ms_p50"), "ort_p90_ms": _get(rt, "onnxruntime", "latency_ms_p90"),
               "fps": _get(rt, "onnxruntime", "fps"), "predict_p50_ms": _get(rt, "prediction", "latency_ms_p50"),
               "size_mb": _get(m, "size_mb"), "params_m": _get(m, "params") / 1e6,
               "peak_memory_mb": _get(rt, "peak_memory_mb"), "torch_p50_ms": _get(rt, "torch_eager_ms_p50"),
               "ort_speedup": _get(rt, "ort_speedup"), "same_boxes": _get(rt, "agreement", "same_boxes"),
               "max_score_diff": _get(rt, "agreement", "max_abs_score_diff"),
               "max_box_diff": _get(rt, "agreement", "max_abs_box_diff"), "train_s": _get(m, "train", "seconds")}
        if isinstance(rt.get("openvino"), dict):
            ov = rt["openvino"]
            row.update(ov_p50_ms=_get(ov, "latency_ms_p50"), ov_same_boxes=_get(ov, "agreement", "same_boxes"),
                       ov_max_box_diff=_get(ov, "agreement", "max_abs_box_diff"), ov_error=ov.get("error"))
        row.update(m.get("provenance") or {})  # the ONNX file's data_hash / config_hash, when it carries them
        rows.append(row)
    return pd.DataFrame(rows)


def data_table(meta: pd.DataFrame | None, frame_stats: pd.DataFrame | None) -> pd.DataFrame:
    """Per weather: frames per split, points per frame (mean/min/max) and LiDAR range statistics."""
    if meta is None or "weather" not in meta.columns:
        return pd.DataFrame()
    df = meta.copy()
    if frame_stats is not None:
        extra = [c for c in frame_stats.columns if c not in df.columns or c == "frame_id"]
        df = df.merge(frame_stats[extra], on="frame_id", how="left")
    g = df.groupby("weather", sort=False)
    out = pd.DataFrame({"n_frames": g.size()})
    if "split" in df.columns:
        for split in ("test", "val"):
            out[f"n_{split}"] = g["split"].apply(lambda s, sp=split: int((s == sp).sum()))
    for col, stats in (("n_points", ("mean", "min", "max")), ("mean_range_m", ("mean",)), ("max_range_m", ("mean",)),
                       ("ground_share", ("mean",)), ("rain_rate_mmh", ("first",)), ("fog_density", ("first",))):
        if col in df.columns:
            for s in stats:
                out[f"{col}_{s}" if s != "first" else col] = g[col].agg(s)
    return out.rename_axis("weather").reset_index()


def fidelity_table(meta: pd.DataFrame | None, clean: str = "ClearNoon", max_range: float = 65.0) -> pd.DataFrame:
    """Per weather, what the LiDAR model did (the simulator's per-frame fidelity columns): returns on the slow car
    per frame (frames where it is within max_range), their share of the clean preset's on the same scenario
    steps, the published extinction model's prediction for that share's power (Marshall-Palmer T^2 at the car),
    returns smeared around the car per return on it, and returns in the air near the sensor per frame."""
    need = {"weather", "scenario_time_s", "slow_car_returns", "slow_car_range_m", "slow_car_t2", "air_returns"}
    if meta is None or not need <= set(meta.columns):
        return pd.DataFrame()
    df = meta[meta["slow_car_range_m"].le(max_range)]
    base = df[df["weather"] == clean].set_index("scenario_time_s")["slow_car_returns"]
    rows = []
    for weather, g in df.groupby("weather", sort=False):
        on = g["slow_car_returns"].sum()
        shared = g[g["scenario_time_s"].isin(base.index)]  # steps the clean preset has too
        ref = base.reindex(shared["scenario_time_s"]).sum()
        rows.append({"weather": weather, "n_frames": len(g), "car_returns": g["slow_car_returns"].mean(),
                     "car_returns_vs_clear": shared["slow_car_returns"].sum() / ref if ref else np.nan,
                     "predicted_T2": g["slow_car_t2"].mean(),
                     "smeared_per_car_return": g["slow_car_smeared"].sum() / on if on else np.nan,
                     "air_returns": meta.loc[meta["weather"] == weather, "air_returns"].mean()})
    return pd.DataFrame(rows)


def stage_table(summary: dict) -> pd.DataFrame:
    """Wall time per pipeline stage (seconds), as recorded by the run."""
    st = summary.get("stage_seconds") or {}
    return pd.DataFrame([{"stage": k, "seconds": v} for k, v in st.items()], columns=["stage", "seconds"])


def _sotif_pass(model: dict, judged: pd.DataFrame) -> str | None:
    """"passed/preventable" car-bodied instances of the SOTIF set, perception verdict (``harness.verdict``); a run
    without it: presets passed by the per-preset view."""
    rows = ((model.get("sotif_space") or {}).get("sotif") or {}).get("summary") or []
    head = next((r for r in rows if r["verdict"] == "perception" and r["body_class"] == "car"), None)
    if head is not None:
        return f"{head['n_pass']}/{head['n']}"
    return f"{int((judged['verdict'] == 'pass').sum())}/{len(judged)}" if len(judged) else None


def overview_table(run: Run, t: dict) -> pd.DataFrame:
    """One row per model: what it is, whether its weights were trained here or published (``weights``), its
    training (epochs, minutes, AP40 3D moderate on the held-out dry frames of the training generator) and
    its key numbers on the SOTIF set (headline AP, mRR, car-bodied preventable instances passed, latency)."""
    rob = t["robustness"].set_index("model") if not t["robustness"].empty else pd.DataFrame()
    rt = t["runtime"].set_index("model") if not t["runtime"].empty else pd.DataFrame()
    so = t["sotif"]
    rows = []
    for name, m in run.summary["models"].items():
        res = run.results[name]
        judged = so[(so["model"] == name) & (so["verdict"] != "n/a")] if not so.empty else so
        rows.append({"model": name, "architecture": m.get("architecture"), "weights": weights(m),
                     "stages": "two" if m.get("two_stage") else "one", "camera": bool(m.get("uses_camera")),
                     "epochs": _get(m, "train", "epochs", default=None),
                     "train min": _get(m, "train", "seconds") / 60,
                     "val AP3D mod": val_ap(m), "val frames": _get(m, "val", "n_frames"),
                     "AP3D": _get(res, "headline", "3d", "0.7"), "AP BEV": _get(res, "headline", "bev", "0.7"),
                     "mRR": rob["mRR"].get(name, np.nan) if len(rob) else np.nan,
                     "SOTIF pass": _sotif_pass(m, judged),
                     "ORT p50 ms": rt["ort_p50_ms"].get(name, np.nan) if len(rt) else np.nan})
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------- output
def fmt_float(v: float, digits: int) -> str:
    """Fixed ``digits`` decimals; tiny non-zero values (agreement errors) in scientific notation."""
    return f"{v:.1e}" if 0 < abs(v) < 0.5 * 10.0 ** -digits else f"{v:.{digits}f}"


def display_cell(v, digits: int) -> str:
    """A table cell as both reports show it: missing as a dash, booleans as yes / no."""
    if v is None or (isinstance(v, (float, np.floating)) and math.isnan(v)):
        return "–"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        return fmt_float(v, digits)
    return str(v)


def _cell(v, digits: int) -> str:
    return display_cell(v, digits).replace("|", "\\|")


def to_markdown(df: pd.DataFrame, digits: int = 2) -> str:
    """A GitHub Markdown table (floats with ``digits`` decimals, missing values as a dash)."""
    if df.empty:
        return "_(no data)_\n"
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    numeric = [pd.api.types.is_numeric_dtype(df[c]) and not pd.api.types.is_bool_dtype(df[c]) for c in df.columns]
    sep = "|" + "|".join("---:" if n else "---" for n in numeric) + "|"
    body = ["| " + " | ".join(_cell(v, digits) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, sep, *body]) + "\n"


def mean_range(values: list) -> dict:
    """{mean, min, max} of the values that are not None (NaN for none)."""
    v = np.array([np.nan if x is None else x for x in values], dtype=float)
    if not len(v) or np.isnan(v).all():
        return {"mean": np.nan, "min": np.nan, "max": np.nan}
    return {"mean": float(np.nanmean(v)), "min": float(np.nanmin(v)), "max": float(np.nanmax(v))}


def val_ap(entry: dict) -> float:
    """AP40 3D moderate @0.7 on the run's val set (``harness.valset``) of a model or draw entry of
    results.json; a run without one: the checkpoint's, on the training set's own val split."""
    if isinstance(entry.get("val"), dict):
        return _get(entry, "val", "3d_moderate")
    return _get(entry, "val_ap", "3d_moderate") if "val_ap" in entry else _get(entry, "train", "val_ap", "3d_moderate")


def draws_table(run: Run) -> pd.DataFrame:
    """With several training draws per model (``run --seeds K``): per model, the mean and range over
    the draws of the val AP40 3D moderate and the headline AP40 3D / BEV @0.7, next to the 95%
    bootstrap interval over frames of draw 0's headline in its narrowest and widest weather
    group (the spread a reader sees without draws), and the CPUs the draws trained on."""
    rows = []
    for name, draws in (run.summary.get("draws") or {}).items():
        ci = [row["headline_ci95"]["3d"] for row in group_rows(run.results.get(name, {}), "weather").values()]
        widths = [hi - lo for lo, hi in ci]
        row = {"model": name, "draws": len(draws), "seeds": ",".join(str(d["seed"]) for d in draws)}
        for key, values in (("val AP3D mod", [val_ap(d) for d in draws]),
                            ("AP3D", [_get(d, "headline", "3d", "0.7", default=None) for d in draws]),
                            ("AP BEV", [_get(d, "headline", "bev", "0.7", default=None) for d in draws])):
            row.update({f"{key} {k}": v for k, v in mean_range(values).items()})
        row["AP3D draw-0 CI95 width, weather min"] = min(widths) if widths else np.nan
        row["AP3D draw-0 CI95 width, weather max"] = max(widths) if widths else np.nan
        # a training rerun on another CPU is another draw: the CPUs that ran the draws' epochs
        places = (m for d in draws for m in provenance.trained_on(d.get("val_history")) if m)
        row["trained on"] = " / ".join(dict.fromkeys(places)) or "not recorded"
        rows.append(row)
    return pd.DataFrame(rows)


def build_tables(run: Run) -> dict[str, pd.DataFrame]:
    """Every table of the report, by name (empty DataFrames for parts the run does not have)."""
    from harness.pairs_run import pair_tables
    weather = group_table(run.results, "weather")
    matrix = headline_matrix(weather)
    sotif = sotif_table(run.summary, order=list(matrix.index))
    t = {
        "kitti_ap": kitti_ap_table(run.results), "recall": recall_table(run.results),
        "weather_headline": headline_with_ci(weather), "weather_detail": weather,
        "rain": rain.rain_long(run.results),
        "robustness": rain.robustness_table(weather, run.meta), "relative_ap": relative_table(matrix),
        "time_of_day": group_table(run.results, "time_of_day"),
        "precipitation_class": group_table(run.results, "precipitation_class"),
        "sotif": sotif, "sotif_matrix": sotif_matrix(sotif), "runtime": runtime_table(run.summary),
        "data_by_weather": data_table(run.meta, run.frame_stats), "stages": stage_table(run.summary),
        "lidar_fidelity": fidelity_table(run.meta),
        # only with several training draws: a run of one draw writes the files it always wrote
        **({"draws": draws_table(run)} if run.summary.get("draws") else {}),
        # only with scenario-space results (harness.report_space)
        **{k: v for k, v in report_space.build(run.summary).items() if not v.empty},
        # the paired comparisons and proposals-alone AP, from the prediction folders (cached: harness.pairs_run)
        **pair_tables(run.run_dir, run.summary),
    }
    return {"overview": overview_table(run, t), **t}


def write_tables(run_dir, tables: dict[str, pd.DataFrame] | None = None) -> dict[str, pd.DataFrame]:
    """Write every table as ``RUN/tables/<name>.csv``, ``.json`` (records) and ``.md``; returns them.
    ``tables`` are those ``build_tables`` built (the report's, so that a render builds them once); built
    from the run's files when not given. Floats are rounded as they are written (``cells.round_floats``);
    the Markdown shows capped and empty AP cells as such (``cells.mark_capped``), the CSV and JSON keep the
    number beside its count column."""
    out = Path(run_dir) / "tables"
    tables = build_tables(load_run(run_dir)) if tables is None else tables
    for name, df in tables.items():
        df = round_floats(df)
        atomic_write_text(out / f"{name}.csv", df.to_csv(index=False, lineterminator="\n"))
        atomic_write_text(out / f"{name}.json", df.to_json(orient="records", indent=1) + "\n")
        atomic_write_text(out / f"{name}.md", to_markdown(mark_capped(df, 2)))
    return tables
