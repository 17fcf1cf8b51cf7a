"""Condition columns as groups: a categorical column or a numeric one with few values groups by value,
a numeric one with more than ``MAX_LEVELS`` distinct values by ``N_BINS`` quantile bins.

One rule for ``evaluate --group-by`` and for the SOTIF pass rates (``harness.sotif_space``): a
swept rain rate, fog visibility or scenario parameter takes as many values as instances, so it is
binned; the 21 presets' rain rates (four values) stay values, as they always were.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

MAX_LEVELS = 10  # distinct numeric values grouped as they are
N_BINS = 4  # quantile bins of a numeric column with more values


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def condition_labels(values: pd.Series, max_levels: int = MAX_LEVELS, n_bins: int = N_BINS) -> pd.Series:
    """Each value's group label (str): the value itself (a numeric column with at most ``max_levels``
    distinct values, or any other column), or "[lo, hi)" of its quantile bin of ``n_bins`` (the last
    bin closed, "[lo, hi]"). Quantile edges that coincide are merged, so a bin is never empty."""
    s = pd.Series(values).reset_index(drop=True)
    numeric = pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s)
    if not numeric or s.nunique() <= max_levels:
        return s.astype(str).set_axis(pd.Series(values).index)
    x = s.to_numpy(float)
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, n_bins + 1)))  # (B + 1,) ascending
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)  # last edge into the last bin
    names = [f"[{_fmt(edges[i])}, {_fmt(edges[i + 1])}{']' if i == len(edges) - 2 else ')'}"
             for i in range(len(edges) - 1)]
    return pd.Series([names[i] for i in idx], index=pd.Series(values).index, dtype=object)
