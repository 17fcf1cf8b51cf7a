"""Figures of the rain story (matplotlib, like ``harness.figures``): AP per model in dry / wet / rain and the
rain grades with their intervals, and the weather heat maps ordered by time of day and rain rate."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from harness import figures
from harness.rain import CONDITIONS, IOUS

CONDITION_STYLE = {  # condition -> (colour, marker): precipitation classes filled, noon rain grades in blues
    "dry": ("#e6a100", "o"), "wet": ("#7fb3d5", "s"), "rain": ("#1f4e9c", "D"),
    "soft rain": ("#9ecae1", "v"), "mid rain": ("#4292c6", "v"), "hard rain": ("#08306b", "v"),
}


def rain_figure(long: pd.DataFrame, labels: dict | None = None) -> Figure:
    """Two panels (IoU 0.5, IoU 0.7): per model, the AP of each condition as a marker with its 95% interval
    (``long``: ``harness.rain.rain_long``); ``labels`` renames models on the axis."""
    models = list(dict.fromkeys(long["model"]))
    conds = [c for c in CONDITIONS if c in set(long["condition"])]
    fig = Figure(figsize=(7.0, 3.9), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True)
    width = 0.8 / max(len(conds), 1)
    for ax, iou in zip(axes, IOUS):
        sub = long[long["iou"] == iou]
        for j, cond in enumerate(conds):
            rows = sub[sub["condition"] == cond].set_index("model").reindex(models)
            xs = np.arange(len(models)) - 0.4 + width * (j + 0.5)
            ap = rows["ap"].to_numpy(dtype=float)
            err = np.abs(np.vstack([ap - rows["ap_lo"].to_numpy(dtype=float), rows["ap_hi"].to_numpy(dtype=float) - ap]))
            colour, marker = CONDITION_STYLE[cond]
            ax.errorbar(xs, ap, yerr=np.nan_to_num(err), fmt=marker, color=colour, ms=5, capsize=2, lw=1,
                        label=cond, gid=f"{iou}:{cond}")
        ax.set_ylabel(f"AP40 3D @{iou} (%)")
        ax.grid(True, axis="y", alpha=0.3)
        for k in range(1, len(models)):
            ax.axvline(k - 0.5, color="#dddddd", lw=0.8)
    axes[0].legend(ncols=len(conds), fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    axes[-1].set_xticks(range(len(models)), [(labels or {}).get(m, m) for m in models], fontsize=9)
    axes[-1].set_xlim(-0.5, len(models) - 0.5)
    return fig


def _time_lines(ax, groups: list[tuple[str, int, int]]) -> None:
    """Horizontal separators between the time-of-day blocks of a heat map, the time of day written at the right."""
    for t, start, stop in groups:
        if start:
            ax.axhline(start - 0.5, color="white", lw=3)
        ax.annotate(t, xy=(1.0, 1.0 - (start + stop) / 2 / sum(s - b for _, b, s in groups)), xycoords="axes fraction",
                    xytext=(4, 0), textcoords="offset points", rotation=90, va="center", fontsize=9)


def ordered_heatmap(matrix: pd.DataFrame, groups: list[tuple[str, int, int]], rates: dict, title: str) -> Figure:
    """``harness.figures.heatmap_figure`` of presets already ordered, rows labelled with their rain rate and the
    time-of-day blocks separated."""
    fig = figures.heatmap_figure(matrix.rename(index=lambda w: _row_label(w, rates)), title)
    _time_lines(fig.axes[0], groups)
    return fig


def _row_label(weather: str, rates: dict) -> str:
    r = rates.get(weather)
    return weather if r is None or (isinstance(r, float) and math.isnan(r)) else f"{weather} ({r:g} mm/h)"


def delta_heatmap(delta: pd.DataFrame, groups: list[tuple[str, int, int]], rates: dict, title: str) -> Figure:
    """AP minus the same time of day's clear preset (points): diverging colours centred on 0, symmetric limits."""
    values = delta.to_numpy(dtype=float)  # (W, M)
    finite = np.abs(values[np.isfinite(values)])
    lim = max(float(finite.max()) if finite.size else 1.0, 1.0)
    fig = Figure(figsize=(2.6 + 1.3 * values.shape[1], 1.2 + 0.32 * values.shape[0]), layout="constrained")
    ax = fig.add_subplot()
    im = ax.imshow(np.ma.masked_invalid(values), cmap="RdBu", vmin=-lim, vmax=lim, aspect="auto")
    ax.set_xticks(range(values.shape[1]), [str(c) for c in delta.columns], rotation=30, ha="right")
    ax.set_yticks(range(values.shape[0]), [_row_label(w, rates) for w in delta.index])
    for (r, c), v in np.ndenumerate(values):
        ax.text(c, r, "–" if math.isnan(v) else f"{v:+.1f}", ha="center", va="center", fontsize=8,
                color="white" if not math.isnan(v) and abs(v) > 0.6 * lim else "black")
    _time_lines(ax, groups)
    fig.colorbar(im, ax=ax, label="AP40 3D @0.7 minus clear (points)", shrink=0.8)
    ax.set_title(title)
    return fig
