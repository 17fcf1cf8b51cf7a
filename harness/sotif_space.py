"""SOTIF over a scenario space: per instance a confirmed detection and a braking margin, pass rates over instances.

A data set simulated with ``--instances N`` holds several instances of the cut-out per weather;
``meta/frames.csv`` names each frame's instance (``instance_key`` = "<weather>#<instance>", the
unit of evidence) and carries the instance's parameters (``sc_*``) and conditions (``rain_rate_mmh``,
``fog_mor_m``, ``road_water``). A data set without these columns is one instance per weather
(``instance_key`` = the weather).

Per instance, over its frames at or after the fast car's lane change (time order):

- a frame is a *hit* when a prediction with score >= the operating threshold has BEV IoU >=
  ``harness.sotif.IOU_BEV_MIN`` with the slow car (``harness.sotif.slow_car_detected``);
- the slow car is *confirmed* at the first frame that is a hit and closes a window of ``n``
  consecutive frames holding at least ``k`` hits (default 3 of 5, as a tracker confirms a track);
- the *braking margin* is the gap left at confirmation if the ego had held its closing speed dv0
  from the first frame after the lane change (``harness.sotif.gap_without_braking``) minus
  ``stopping_distance(dv0)`` with the model's measured onnxruntime latency (p50) added to the
  reaction time. The instance passes when the margin is >= 0; never confirmed = fail;
- the instance is *feasible* when an ideal detector passes it: one that hits every frame in which the
  slow car is labelled and has no latency (``ideal_margin_m`` >= 0). An infeasible instance (the
  scenario leaves no room to brake whatever the detector) says nothing about the detector, so pass
  rates count feasible instances only and name how many were left out.

Pass rates over instances carry a 95 % Wilson score interval. Pure functions first, then the driver.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import binomtest

from harness import sotif
from harness.conditions import N_BINS, condition_labels
from harness.core.braking import T_REACT_S, stopping_distance
from harness.core.kitti import KittiError

CONFIRM_K, CONFIRM_N = 3, 5  # hits within consecutive frames that confirm the slow car
MIN_INSTANCES = 5  # fewer instances in a condition bin: too few to judge
CONDITION_COLUMNS = ("rain_rate_mmh", "fog_mor_m", "road_water", "sc_slow_reflectance", "sc_ego_speed_kmh",
                     "sc_slow_speed_kmh", "sc_cutout_gap_m", "sc_lane_change_s", "sc_lateral_offset_m",
                     "sc_slow_body", "sc_slow_paint", "sc_fast_body", "precipitation_class")
AXIS_COLUMNS = {"rain": "rain_rate_mmh", "fog": "fog_mor_m", "water": "road_water"}  # sweep axis -> its column
FRAME_COLUMNS = ("rain_rate_mmh", "fog_mor_m", "sc_slow_reflectance", "precipitation_class")  # kept per frame


# ----------------------------------------------------------------------------- pure functions
def confirmed_index(hits, k: int = CONFIRM_K, n: int = CONFIRM_N) -> int | None:
    """Index of the frame at which the slow car is confirmed: the first hit i such that frames
    i - n + 1 .. i (those that exist) hold at least ``k`` hits; None when no window does."""
    if not 1 <= k <= n:
        raise ValueError(f"confirmation needs 1 <= k <= n, got k={k}, n={n}")
    h = np.asarray(hits, dtype=np.int64)  # (F,) 1 = hit
    if h.size == 0:
        return None
    csum = np.cumsum(h)
    window = csum - np.r_[np.zeros(n, np.int64), csum[:-n]][: h.size]  # (F,) hits in the n frames ending at i
    idx = np.flatnonzero((window >= k) & (h == 1))
    return int(idx[0]) if idx.size else None


def braking_margin(d0: float, closing_speed_mps: float, dt_s: float, latency_s: float) -> float:
    """Metres to spare: gap left ``dt_s`` after d0 at a held closing speed, minus the stopping distance
    with ``latency_s`` added to the reaction time (negative: the ego cannot stop in time)."""
    gap = sotif.gap_without_braking(d0, closing_speed_mps, dt_s)
    return gap - stopping_distance(closing_speed_mps, t_react=T_REACT_S + latency_s)


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (NaNs for n = 0)."""
    if n == 0:
        return float("nan"), float("nan")
    ci = binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def rate_row(passed) -> dict:
    """``{n, n_pass, rate, lo, hi, too_few}`` of a sequence of pass verdicts (bool)."""
    p = np.asarray(passed, dtype=bool)
    lo, hi = wilson_interval(int(p.sum()), p.size)
    return {"n": int(p.size), "n_pass": int(p.sum()), "rate": float(p.mean()) if p.size else float("nan"),
            "lo": lo, "hi": hi, "too_few": bool(p.size < MIN_INSTANCES)}


def pass_rates(instances: pd.DataFrame, column: str) -> pd.DataFrame:
    """Pass rate with its Wilson interval per value (or bin, ``harness.conditions``) of ``column``, over the
    feasible instances when the rows say which are (``n_infeasible``: those left out). A numeric column gets
    as many quantile bins as keep ``MIN_INSTANCES`` instances in each (at most ``conditions.N_BINS``); a
    column with one value in these instances tells nothing and gives no rows."""
    cols = ["column", "bin", "n", "n_pass", "rate", "lo", "hi", "too_few", "n_infeasible"]
    if column not in instances.columns or instances.empty or instances[column].isna().all():
        return pd.DataFrame(columns=cols)
    df = instances[instances[column].notna()]
    if pd.api.types.is_numeric_dtype(df[column]) and df[column].nunique() < 2 and len(df) > 1:
        return pd.DataFrame(columns=cols)
    bins = max(1, min(N_BINS, len(df) // MIN_INSTANCES))
    labels = condition_labels(df[column], max_levels=bins, n_bins=bins)
    feasible = df["feasible"].fillna(True).astype(bool) if "feasible" in df.columns else pd.Series(True, df.index)
    rows = [{"column": column, "bin": b,
             **rate_row(df.loc[(labels == b) & feasible, "pass"].astype(bool)),
             "n_infeasible": int(((labels == b) & ~feasible).sum())}
            for b in _ordered(labels, df[column])]
    return pd.DataFrame(rows, columns=cols)


def _ordered(labels: pd.Series, values: pd.Series) -> list:
    """The bins of a numeric column from its lowest values up; any other column's in order of appearance."""
    if not pd.api.types.is_numeric_dtype(values) or pd.api.types.is_bool_dtype(values):
        return list(pd.unique(labels))
    return list(values.groupby(labels).min().sort_values(kind="stable").index)


def boundary_grid(frames: pd.DataFrame, y: str, x_edges, y_edges) -> tuple[np.ndarray, np.ndarray]:
    """(hits, counts), each (len(y_edges) - 1, len(x_edges) - 1): slow-car frames binned by distance
    (``distance_m``, columns) and ``y`` (rows), bins closed on the left (the last on both sides); frames
    outside the edges or without a ``y`` value (a data set without that condition) are dropped."""
    x = frames["distance_m"].to_numpy(float)
    yv = frames[y].to_numpy(float)
    ok = ~np.isnan(x) & ~np.isnan(yv)
    x, yv, hit = x[ok], yv[ok], frames["hit"].to_numpy(bool)[ok]
    counts, _, _ = np.histogram2d(yv, x, bins=[np.asarray(y_edges, float), np.asarray(x_edges, float)])
    hits, _, _ = np.histogram2d(yv[hit], x[hit], bins=[np.asarray(y_edges, float), np.asarray(x_edges, float)])
    return hits.astype(np.int64), counts.astype(np.int64)


# ----------------------------------------------------------------------------- driver
def instance_keys(frames: pd.DataFrame) -> pd.Series:
    """Each frame's instance: ``instance_key`` when the data set has it, else its weather."""
    return frames["instance_key"].astype(str) if "instance_key" in frames.columns else frames["weather"].astype(str)


def _instance(data_dir: Path, predictions_dir: Path, frames: pd.DataFrame, threshold: float, latency_s: float,
              k: int, n: int) -> tuple[dict, pd.DataFrame]:
    """One instance's verdict and its slow-car frames (distance, hit) at or after the lane change."""
    first = frames.iloc[0]
    row = {"instance_key": str(first["_key"]), "weather": str(first["weather"]),
           "instance": int(first["instance"]) if "instance" in frames.columns else 0,
           **{c: first[c] for c in (*CONDITION_COLUMNS, "sweep_axis") if c in frames.columns},
           "n_frames": 0, "detected": False, "confirmed": False, "time_after_lane_change_s": None,
           "gap_m": None, "closing_speed_mps": None, "stopping_distance_m": None, "margin_m": None, "pass": None,
           "ideal_margin_m": None, "feasible": None}
    t_lc = float(first["lane_change_time_s"])
    after = frames[(frames["scenario_time_s"] >= t_lc - 1e-6) & (frames["slow_car_label_index"] >= 0)]
    if np.isnan(t_lc) or after.empty:
        return row, pd.DataFrame()
    hits, slow_boxes = sotif.slow_car_track(data_dir, predictions_dir, after, threshold)
    ref = after.iloc[0]
    dv0, d0 = float(ref["ego_speed_mps"] - ref["slow_car_speed_mps"]), sotif.rear_distance(slow_boxes[0])
    t0 = float(ref["scenario_time_s"])
    ideal = confirmed_index(np.ones(len(after), bool), k, n)  # every labelled frame a hit
    if ideal is not None:
        row["ideal_margin_m"] = braking_margin(d0, dv0, float(after.iloc[ideal]["scenario_time_s"]) - t0, 0.0)
    row["feasible"] = row["ideal_margin_m"] is not None and bool(row["ideal_margin_m"] >= 0)
    row.update(n_frames=len(after), detected=bool(any(hits)), closing_speed_mps=dv0,
               stopping_distance_m=stopping_distance(dv0, t_react=T_REACT_S + latency_s), **{"pass": False})
    i = confirmed_index(hits, k, n)
    if i is not None:
        t = float(after.iloc[i]["scenario_time_s"])
        row.update(confirmed=True, time_after_lane_change_s=t - t_lc, gap_m=sotif.gap_without_braking(d0, dv0, t - t0),
                   margin_m=braking_margin(d0, dv0, t - t0, latency_s))
        row["pass"] = bool(row["margin_m"] >= 0)
    per_frame = pd.DataFrame({"instance_key": row["instance_key"],
                              "distance_m": [sotif.rear_distance(b) for b in slow_boxes], "hit": hits,
                              **{c: after[c].to_numpy() for c in FRAME_COLUMNS if c in after.columns}})
    return row, per_frame


def instance_view(data_dir, predictions_dir, threshold: float, latency_s: float, split: str = "test",
                  k: int = CONFIRM_K, n: int = CONFIRM_N) -> dict:
    """Per instance of ``split``: the confirmed detection and braking margin (module docstring).

    ``{"rule": {k, n, latency_s, threshold}, "instances": [row, ...], "frames": {column: [...]}}``; a row
    holds instance_key, weather, instance, the instance's conditions, n_frames, detected (any hit),
    confirmed, time_after_lane_change_s, gap_m, closing_speed_mps, stopping_distance_m (latency
    included), margin_m and pass (None: no lane change in the data). ``frames`` lists the slow-car
    frames at or after the lane change (instance_key, distance_m, hit and per-frame conditions).
    """
    data_dir, predictions_dir = Path(data_dir), Path(predictions_dir)
    if not predictions_dir.is_dir():
        raise KittiError(predictions_dir, "prediction folder not found")
    meta = sotif.load_meta(data_dir)
    ids = sotif.split_ids(data_dir, split)
    if not ids:
        raise KittiError(data_dir / "ImageSets" / f"{split}.txt", "no frames in the split")
    frames = meta[meta["frame_id"].isin(set(ids))].copy()
    frames["_key"] = instance_keys(frames)
    keys = pd.unique(frames["_key"])  # data set order
    frames = frames.sort_values("scenario_time_s", kind="stable")
    rows, per_frame = [], []
    for key in keys:
        row, fr = _instance(data_dir, predictions_dir, frames[frames["_key"] == key], threshold, latency_s, k, n)
        rows.append({c: (v.item() if isinstance(v, np.generic) else v) for c, v in row.items()})
        per_frame.append(fr)
    table = pd.concat(per_frame, ignore_index=True) if any(len(f) for f in per_frame) else pd.DataFrame()
    return {"rule": {"k": k, "n": n, "latency_s": float(latency_s), "threshold": float(threshold)},
            "instances": rows, "frames": {c: table[c].tolist() for c in table.columns}}
