"""The rain story that leads the report, and the weather tables read against clear weather.

Pure functions from a run's loaded result files (``harness.tables.Run``) to DataFrames:

- ``rain_long``: per model, IoU (0.5 and 0.7) and condition, the headline AP40 3D (all distances, no
  2D-height filter) and its 95% bootstrap interval over frames. Conditions: the precipitation
  classes dry / wet / rain (all times of day) and the rain grades soft / mid / hard, which are the
  noon rain presets (``RAIN_GRADES``: 4.5, 18 and 50 mm/h, the README's columns).
- ``preset_order``: the weather presets grouped by time of day, by rain rate then road water within.
- ``clear_delta``: AP minus the same time of day's clear preset (percentage points).
- ``robustness_table``: relative AP and mRR with intervals; the worst preset is a rain or wet one.
- ``lidar_twins``: presets whose LiDAR conditions (rain rate, road water) are the same.

Intervals of ratios come from the recorded percentile intervals by the delta method: a standard
error s = (hi - lo) / (2 * 1.96) per group (disjoint frames, so independent), then
var(a / c) = (s_a^2 + (a / c)^2 s_c^2) / c^2.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from harness.groups import CLEAN_PRESETS, corrupt_presets, group_rows, headline_matrix, relative_ap

PRECIPITATION = ("dry", "wet", "rain")
RAIN_GRADES = (("soft rain", "SoftRainNoon"), ("mid rain", "MidRainyNoon"), ("hard rain", "HardRainNoon"))
CONDITIONS = (*PRECIPITATION, *(g for g, _ in RAIN_GRADES))
IOUS = ("0.5", "0.7")
TIMES = ("Noon", "Sunset", "Night")
Z95 = 1.959964  # two-sided 95% normal quantile
LONG_COLUMNS = ["model", "iou", "condition", "group", "n_frames", "n_car", "ap", "ap_lo", "ap_hi"]


def _interval(row: dict, iou: str) -> tuple[float, float]:
    """The group's 95% interval of the headline AP40 3D at ``iou`` (NaN when not recorded)."""
    ci = row.get("headline_ci95" if iou == "0.7" else f"headline_ci95_{iou}", {}).get("3d")
    return (float(ci[0]), float(ci[1])) if ci else (np.nan, np.nan)


def rain_long(results: dict) -> pd.DataFrame:
    """Long table: one row per (model, IoU, condition) with the AP, its interval and the frames and cars behind it."""
    rows = []
    for name, res in results.items():
        precip, weather = group_rows(res, "precipitation_class"), group_rows(res, "weather")
        sources = [(c, c, precip.get(c)) for c in PRECIPITATION] + [(g, p, weather.get(p)) for g, p in RAIN_GRADES]
        for iou in IOUS:
            for cond, group, row in sources:
                if row is None:
                    continue
                lo, hi = _interval(row, iou)
                rows.append({"model": name, "iou": iou, "condition": cond, "group": group, "n_frames": row["n_frames"],
                             "n_car": row["n_car"], "ap": float(row["headline"]["3d"][iou]), "ap_lo": lo, "ap_hi": hi})
    return pd.DataFrame(rows, columns=LONG_COLUMNS)


def _cell(ap: float, lo: float, hi: float) -> str:
    if np.isnan(ap):
        return "–"
    return f"{ap:.1f}" if np.isnan(lo) else f"{ap:.1f} [{lo:.1f}, {hi:.1f}]"


def rain_display(long: pd.DataFrame) -> pd.DataFrame:
    """Rows (model, IoU), columns the conditions present, cells "AP [lo, hi]"."""
    if long.empty:
        return pd.DataFrame()
    conds = [c for c in CONDITIONS if c in set(long["condition"])]
    out = []
    for (name, iou), sub in long.groupby(["model", "iou"], sort=False):
        by = sub.set_index("condition")
        out.append({"model": name, "IoU": iou,
                    **{c: _cell(*by.loc[c, ["ap", "ap_lo", "ap_hi"]]) if c in by.index else "–" for c in conds}})
    df = pd.DataFrame(out)
    order = {iou: i for i, iou in enumerate(IOUS)}  # IoU 0.5 (the README's columns) first, models in run order
    return df.sort_values("IoU", key=lambda s: s.map(order), kind="stable").reset_index(drop=True)


# ----------------------------------------------------------------------------- presets against clear weather
def preset_facts(meta: pd.DataFrame | None) -> pd.DataFrame:
    """Per preset (index): time of day, rain rate (mm/h) and road water cover in [0, 1]
    (max(deposits, wetness, precipitation) / 100, as the simulator's wet-road model); empty without meta."""
    need = {"weather", "time_of_day", "rain_rate_mmh", "precipitation", "precipitation_deposits", "wetness", "cloudiness"}
    if meta is None or not need <= set(meta.columns):
        return pd.DataFrame()
    first = meta.drop_duplicates("weather").set_index("weather")
    water = first[["precipitation_deposits", "wetness", "precipitation"]].max(axis=1).clip(upper=100.0) / 100.0
    return pd.DataFrame({"time_of_day": first["time_of_day"].astype(str), "rain_rate_mmh": first["rain_rate_mmh"],
                         "water": water, "cloudiness": first["cloudiness"]})


def preset_order(weathers, meta: pd.DataFrame | None) -> list[str]:
    """``weathers`` grouped by time of day (Noon, Sunset, Night), by rain rate, road water and cloudiness within;
    the given order without meta; presets the meta lacks last."""
    facts = preset_facts(meta)
    weathers = list(weathers)
    if facts.empty:
        return weathers
    known = [w for w in weathers if w in facts.index]
    rank = {t: i for i, t in enumerate(TIMES)}
    key = lambda w: (rank.get(facts.loc[w, "time_of_day"], len(TIMES)), facts.loc[w, "rain_rate_mmh"],
                     facts.loc[w, "water"], facts.loc[w, "cloudiness"])
    return sorted(known, key=key) + [w for w in weathers if w not in facts.index]


def clear_of_time(meta: pd.DataFrame | None) -> dict[str, str]:
    """``{time of day: its clear preset}``: no rain, no road water, least cloud (ClearNoon, ClearSunset, ClearNight)."""
    facts = preset_facts(meta)
    if facts.empty:
        return {}
    dry = facts[(facts["rain_rate_mmh"] == 0) & (facts["water"] == 0)]
    return {t: g.sort_values("cloudiness", kind="stable").index[0] for t, g in dry.groupby("time_of_day")}


def clear_delta(matrix: pd.DataFrame, meta: pd.DataFrame | None) -> pd.DataFrame:
    """AP minus the AP of the same time of day's clear preset (points), same shape as ``matrix``; NaN where the
    time of day has no clear preset in the matrix."""
    facts, clear = preset_facts(meta), clear_of_time(meta)
    out = pd.DataFrame(np.nan, index=matrix.index, columns=matrix.columns)
    for w in matrix.index:
        ref = clear.get(facts.loc[w, "time_of_day"]) if w in facts.index else None
        if ref in matrix.index:
            out.loc[w] = matrix.loc[w] - matrix.loc[ref]
    return out


def time_groups(order: list[str], meta: pd.DataFrame | None) -> list[tuple[str, int, int]]:
    """(time of day, first row, last row + 1) of each run of ``order`` sharing a time of day."""
    facts = preset_facts(meta)
    times = [facts.loc[w, "time_of_day"] if w in facts.index else "?" for w in order]
    groups, start = [], 0
    for i in range(1, len(times) + 1):
        if i == len(times) or times[i] != times[start]:
            groups.append((times[start], start, i))
            start = i
    return groups


def lidar_twins(meta: pd.DataFrame | None) -> list[list[str]]:
    """Groups of presets with the same rain rate and road water (the LiDAR sees only those and sunlight noise),
    in data set order; single presets included."""
    facts = preset_facts(meta)
    if facts.empty:
        return []
    return [list(g.index) for _, g in facts.groupby(["rain_rate_mmh", "water"], sort=False)]


# ----------------------------------------------------------------------------- robustness with intervals
def _se(lo, hi):
    """Standard error from a 95% interval (normal approximation)."""
    return (np.asarray(hi, dtype=float) - np.asarray(lo, dtype=float)) / (2 * Z95)


def ratio_interval(a: float, s_a: float, c: float, s_c: float) -> tuple[float, float, float]:
    """(a / c, lo, hi): the ratio of two independent estimates with standard errors, delta-method 95% interval."""
    if not c > 0:
        return np.nan, np.nan, np.nan
    r = a / c
    s = np.sqrt(s_a ** 2 + r ** 2 * s_c ** 2) / c
    return r, r - Z95 * s, r + Z95 * s


def reading(lo: float, hi: float) -> str:
    """What an interval of a relative AP says: a loss or gain only when it excludes 1."""
    if np.isnan(lo) or np.isnan(hi):
        return "–"
    return "measurable loss" if hi < 1 else ("measurable gain" if lo > 1 else "no measurable loss")


def robustness_table(long: pd.DataFrame, meta: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per model (``long``: ``groups.group_table`` by weather): clean AP (mean of ClearNoon and ClearSunset), mRR
    (mean relative AP over the rain/wet presets, Robo3D) with its interval and reading, and the worst rain/wet
    preset with its relative AP and interval (a clean preset is never named)."""
    cols = ["model", "clean_ap3d", "mRR", "mRR_lo", "mRR_hi", "reading", "n_corrupt_presets", "worst_preset",
            "worst_rel", "worst_rel_lo", "worst_rel_hi"]
    if long.empty:
        return pd.DataFrame(columns=cols)
    ap, se = headline_matrix(long), _se(headline_matrix(long, value="ap3d_lo"), headline_matrix(long, value="ap3d_hi"))
    se = pd.DataFrame(se, index=ap.index, columns=ap.columns)
    clean_ap, rel = relative_ap(ap)
    clean = [w for w in CLEAN_PRESETS if w in ap.index]
    corrupt = corrupt_presets(list(ap.index), meta)
    rows = []
    for name in ap.columns:
        s_c = float(np.sqrt((se.loc[clean, name] ** 2).sum()) / len(clean)) if clean else np.nan
        m = ratio_interval(float(ap.loc[corrupt, name].mean()), float(np.sqrt((se.loc[corrupt, name] ** 2).sum()))
                           / len(corrupt), float(clean_ap[name]), s_c) if corrupt else (np.nan,) * 3
        r = rel.loc[corrupt, name].dropna()
        worst = r.idxmin() if len(r) else None
        w = ratio_interval(ap.loc[worst, name], se.loc[worst, name], clean_ap[name], s_c) if worst else (np.nan,) * 3
        rows.append({"model": name, "clean_ap3d": clean_ap[name], "mRR": m[0], "mRR_lo": m[1], "mRR_hi": m[2],
                     "reading": reading(m[1], m[2]), "n_corrupt_presets": len(corrupt), "worst_preset": worst,
                     "worst_rel": w[0], "worst_rel_lo": w[1], "worst_rel_hi": w[2]})
    return pd.DataFrame(rows, columns=cols)


def robustness_display(rob: pd.DataFrame) -> pd.DataFrame:
    """The summary as the reader sees it: "0.93 [0.85, 1.01]" cells."""
    if rob.empty:
        return rob
    fmt = lambda v, lo, hi: "–" if np.isnan(v) else f"{v:.2f} [{lo:.2f}, {hi:.2f}]"
    return pd.DataFrame({
        "model": rob["model"], "clean AP 3D": rob["clean_ap3d"],
        "mRR [95%]": [fmt(*v) for v in zip(rob["mRR"], rob["mRR_lo"], rob["mRR_hi"])], "reading": rob["reading"],
        "worst rain/wet preset": rob["worst_preset"],
        "its relative AP [95%]": [fmt(*v) for v in zip(rob["worst_rel"], rob["worst_rel_lo"], rob["worst_rel_hi"])],
        "its reading": [reading(lo, hi) for lo, hi in zip(rob["worst_rel_lo"], rob["worst_rel_hi"])]})
