"""Pass rates over scenario instances and the detection grid of the report's maps (``harness.report_space``).

An instance verdict row (``harness.verdict``) says whether the instance is preventable (``feasible`` here: a
reference perception passes it) and whether a model passed it (``pass``). Pass rates count the preventable
instances of a condition bin (``harness.conditions``: quantile bins of a numeric column that keep at least
``MIN_INSTANCES`` instances each) and carry a 95 % Wilson score interval over instances.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.stats import binomtest

from harness.conditions import N_BINS, condition_labels

MIN_INSTANCES = 5  # fewer instances in a condition bin: too few to judge


# ----------------------------------------------------------------------------- pure functions
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
    feasible (preventable) instances when the rows say which are (``n_infeasible``: those left out). A numeric column gets
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
