"""A run's results by group (weather preset, time of day, precipitation class), and read against clear weather.

Pure functions from the loaded result dicts (``harness.tables.Run.results``) to dicts and DataFrames, which
both the tables (``harness.tables``) and the rain story (``harness.rain``) build on:

- ``group_rows``: one results file's rows of a grouping; ``group_table``: the long table over models;
- ``headline_matrix`` / ``headline_with_ci``: the group x model headline AP40 3D (with its interval);
- ``corrupt_presets``, ``relative_ap``, ``relative_table``: the rain/wet presets and the AP relative to
  the clean presets (``CLEAN_PRESETS``).
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from harness.cells import DISTANCE_BINS

CLEAN_PRESETS = ("ClearNoon", "ClearSunset")
CORRUPT_CLASSES = ("rain", "wet")  # precipitation classes whose presets enter the mRR


def group_rows(res: dict, column: str) -> dict:
    """``{value: row}`` of one results file grouped by ``column`` (empty when not evaluated)."""
    by = res.get("groups_by", {})
    if column in by:
        return by[column]["rows"]
    g = res.get("groups")
    return g["rows"] if g and g.get("column") == column else {}


def _group_record(row: dict) -> dict:
    lo, hi = row["headline_ci95"]["3d"]
    rec = row["recall"].get("rcnn", {})
    return {"n_frames": row["n_frames"], "n_car": row["n_car"], "ap3d": row["headline"]["3d"]["0.7"],
            "ap3d_lo": lo, "ap3d_hi": hi, "ap_bev": row["headline"]["bev"]["0.7"],
            "ap3d_0.5": row["headline"]["3d"]["0.5"],
            "kitti_mod_3d": row["kitti_moderate"]["3d"], "kitti_mod_bev": row["kitti_moderate"]["bev"],
            **{f"ap3d_{b}m": row["distance"]["3d"]["0.7"][b] for b in DISTANCE_BINS},
            # the boxes behind each AP (an AP40 over n boxes is at most (n - 1) / 40; older results lack them)
            "n_gt_kitti_mod": row.get("n_gt_kitti_moderate", np.nan),
            **{f"n_gt_{b}m": row.get("n_gt", {}).get(b, np.nan) for b in DISTANCE_BINS},
            "recall@0.5": 100.0 * rec.get("0.5", np.nan), "recall@0.7": 100.0 * rec.get("0.7", np.nan)}


def group_table(results: dict, column: str = "weather") -> pd.DataFrame:
    """Long table: one row per (group value, model) with headline AP40 3D @0.7 and its 95% CI,
    BEV, KITTI moderate, distance bins and RCNN recall."""
    rows = [{column: value, "model": name, **_group_record(row)}
            for name, res in results.items() for value, row in group_rows(res, column).items()]
    if not rows:
        return pd.DataFrame(columns=[column, "model"])
    df = pd.DataFrame(rows)
    order = list(dict.fromkeys(df[column]))
    df[column] = pd.Categorical(df[column], categories=order, ordered=True)
    return df.sort_values([column], kind="stable").astype({column: str}).reset_index(drop=True)


def headline_matrix(long: pd.DataFrame, column: str = "weather", value: str = "ap3d") -> pd.DataFrame:
    """Wide ``column`` x model matrix of one value of ``group_table`` (group order kept)."""
    if long.empty:
        return pd.DataFrame()
    order = list(dict.fromkeys(long[column]))
    models = list(dict.fromkeys(long["model"]))
    wide = long.pivot(index=column, columns="model", values=value).reindex(index=order, columns=models)
    wide.columns.name = None
    return wide


def headline_with_ci(long: pd.DataFrame, column: str = "weather") -> pd.DataFrame:
    """The main table: per group value, each model's headline AP and its 95% interval."""
    if long.empty:
        return pd.DataFrame(columns=[column])
    out = pd.DataFrame({column: list(dict.fromkeys(long[column]))})
    for name in dict.fromkeys(long["model"]):
        sub = long[long["model"] == name].set_index(column)
        for key, suffix in (("ap3d", ""), ("ap3d_lo", " lo"), ("ap3d_hi", " hi")):
            out[f"{name}{suffix}"] = out[column].map(sub[key])
    return out


# ----------------------------------------------------------------------------- against clear weather
def corrupt_presets(weathers, meta: pd.DataFrame | None) -> list[str]:
    """Rain/wet presets: by the meta's precipitation_class, else by name ("Rain", "Wet")."""
    if meta is not None and {"weather", "precipitation_class"} <= set(meta.columns):
        cls = meta.drop_duplicates("weather").set_index("weather")["precipitation_class"]
        return [w for w in weathers if cls.get(w) in CORRUPT_CLASSES]
    return [w for w in weathers if "Rain" in w or "Wet" in w]


def relative_ap(matrix: pd.DataFrame, clean=CLEAN_PRESETS) -> tuple[pd.Series, pd.DataFrame]:
    """(clean AP per model, AP / clean AP per weather and model); NaN where the clean AP is 0 or absent."""
    present = [w for w in clean if w in matrix.index]
    clean_ap = matrix.loc[present].mean(axis=0) if present else pd.Series(np.nan, index=matrix.columns)
    return clean_ap, matrix.div(clean_ap.where(clean_ap > 0), axis=1)


def relative_table(matrix: pd.DataFrame) -> pd.DataFrame:
    """Per weather x model: headline AP relative to the model's clean AP (1.0 = as in clear weather)."""
    if matrix.empty:
        return pd.DataFrame()
    return relative_ap(matrix)[1].rename_axis("weather").reset_index()
