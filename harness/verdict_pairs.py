"""Two models' SOTIF verdicts on the same instances, compared paired: an exact McNemar test on pass / fail and a
paired bootstrap on the deceleration each leaves (``harness.verdict`` rows).

Per set, verdict kind and pair of models, over the preventable car-bodied instances both were judged on:

- McNemar: of the instances exactly one of the two passes (``a_only`` + ``b_only``), is the split further from
  even than chance? Two-sided exact binomial p-value (scipy.stats.binomtest).
- a_req: the difference of the two models' median a_req (inf: never confirmed; a median is defined while fewer
  than half are), with a 95 % interval from a paired bootstrap that resamples the independent unit with
  replacement and keeps each unit's instances together: the drive (an instance's number, shared by its weather
  copies: the SOTIF set's presets re-run the same drives) or, where every instance is its own drive (a sweep set),
  the instance.

``apart``: McNemar's p < 0.05. Pure functions on the instance table; the report's tables/sotif_pairs.csv.
"""
from __future__ import annotations

from itertools import combinations

import numpy as np
import pandas as pd
from scipy.stats import binomtest

PAIR_COLUMNS = ("set", "verdict", "model_a", "model_b", "n_instances", "unit", "n_units", "a_only", "b_only",
                "mcnemar_p", "median_a_req_a", "median_a_req_b", "diff_median_a_req", "ci_lo", "ci_hi", "apart")


def mcnemar_p(a_only: int, b_only: int) -> float:
    """Two-sided exact McNemar p-value of the discordant counts (1.0 when there are none)."""
    n = a_only + b_only
    return 1.0 if n == 0 else float(binomtest(int(a_only), int(n), 0.5).pvalue)


def drive_of(instance: pd.Series) -> pd.Series:
    """An instance's drive: the number after "#" in its key ("ClearNoon#1" and "HardRainNight#1": drive 1)."""
    return instance.astype(str).str.split("#").str[-1]


def median_diff(a: np.ndarray, b: np.ndarray) -> float:
    """median(a) - median(b); 0 when both medians are inf (both mostly never confirmed)."""
    ma, mb = float(np.median(a)), float(np.median(b))
    return 0.0 if ma == mb == np.inf else ma - mb


def paired_bootstrap_median(a: np.ndarray, b: np.ndarray, units: np.ndarray, n: int, seed: int) -> tuple[float, float]:
    """95 % interval of ``median_diff(a, b)`` over ``n`` resamples of the units (a unit's instances together);
    percentiles taken as sample values (inverted CDF), so an end may be infinite."""
    rng = np.random.default_rng(seed)
    labels, inverse = np.unique(units, return_inverse=True)
    members = [np.flatnonzero(inverse == k) for k in range(len(labels))]
    diffs = np.empty(n)
    for r in range(n):
        idx = np.concatenate([members[k] for k in rng.integers(0, len(members), len(members))])
        diffs[r] = median_diff(a[idx], b[idx])
    return (float(np.percentile(diffs, 2.5, method="inverted_cdf")),
            float(np.percentile(diffs, 97.5, method="inverted_cdf")))


def pair_table(instances: pd.DataFrame, n_boot: int = 1000, seed: int = 0) -> pd.DataFrame:
    """Every pair of models per set and verdict kind (module docstring); columns PAIR_COLUMNS."""
    rows = []
    judged = instances[instances["preventable"].astype(bool) & (instances["body_class"] == "car")]
    for (data_set, kind), g in judged.groupby(["set", "verdict"], sort=False):
        wide_pass = g.pivot_table(index="instance", columns="model", values="passed", aggfunc="first")
        wide_a = g.pivot_table(index="instance", columns="model", values="a_req_mps2", aggfunc="first")
        units = drive_of(wide_pass.index.to_series()).to_numpy()
        unit = "drives" if len(np.unique(units)) < len(units) else "instances"
        units = units if unit == "drives" else wide_pass.index.to_numpy()
        for ma, mb in combinations(dict.fromkeys(g["model"]), 2):
            both = wide_pass[[ma, mb]].notna().all(axis=1).to_numpy()
            pa, pb = wide_pass[ma].to_numpy()[both].astype(bool), wide_pass[mb].to_numpy()[both].astype(bool)
            aa, ab = wide_a[ma].to_numpy(float)[both], wide_a[mb].to_numpy(float)[both]
            a_only, b_only = int((pa & ~pb).sum()), int((~pa & pb).sum())
            lo, hi = paired_bootstrap_median(aa, ab, units[both], n_boot, seed) if both.any() else (np.nan, np.nan)
            p = mcnemar_p(a_only, b_only)
            rows.append({"set": data_set, "verdict": kind, "model_a": ma, "model_b": mb, "n_instances": int(both.sum()),
                         "unit": unit, "n_units": int(len(np.unique(units[both]))), "a_only": a_only,
                         "b_only": b_only, "mcnemar_p": p, "median_a_req_a": float(np.median(aa)) if both.any() else np.nan,
                         "median_a_req_b": float(np.median(ab)) if both.any() else np.nan,
                         "diff_median_a_req": median_diff(aa, ab) if both.any() else np.nan,
                         "ci_lo": lo, "ci_hi": hi, "apart": bool(p < 0.05)})
    return pd.DataFrame(rows, columns=list(PAIR_COLUMNS))
