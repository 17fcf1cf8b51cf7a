"""The report's paired comparisons, proposals-alone AP and training-draw notes (``harness.report`` lays
them out; everything comes from ``tables/pairs``, ``tables/proposals`` and ``results.json``).

The two draws of the sample of 2026-11-27 (docs/results.md, History, "Training draws") differed by up to
``EARLIER_VAL_SPREAD`` points in val AP (SECOND 84.8 / 91.0) and ``EARLIER_HEADLINE_SPREAD`` in the SOTIF
headline (Part-A2 74.0 / 56.5): what a reader should expect of a row that is one draw, until a run of its
own has several.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from harness.figures import colour
from harness.pairs_run import bootstrap_settings
from harness.tables import mean_range, val_ap

EARLIER_VAL_SPREAD = 6.2  # points, the sample of 2026-11-27 (docs/results.md, History): SECOND's val AP, seeds 0 / 1
EARLIER_HEADLINE_SPREAD = 17.5  # points, the same sample: Part-A2's SOTIF headline over seeds 0 / 1
METRIC_NAMES = {"val_ap3d_moderate": "val AP40 3D moderate @0.7", "headline_ap3d": "SOTIF headline AP40 3D @0.7"}

COLUMN_NAMES = {"model_a": "model A", "model_b": "model B", "mean_diff": "A - B", "ci_lo": "95% low",
                "ci_hi": "95% high", "n_units": "frames or instances", "n_draws_a": "draws A", "n_draws_b": "draws B",
                "n_draws": "draws"}
HOW_TO_READ = {
    "pairs": "A pair is apart (one model better) only when its interval excludes 0; an interval across 0 is a "
             "tie the data and the draws cannot break.",
    "proposals": "A final AP below the proposals' AP means the second stage made its own first stage worse.",
}


def draws_note(summary: dict) -> str:
    """How many training draws a row of an accuracy table is, and how far a draw moves it."""
    draws = summary.get("draws") or {}
    k = max((len(v) for v in draws.values()), default=1)
    if k <= 1:
        return (f"Each row is one training draw; in an earlier sample (2026-11-27, docs/results.md, History) two "
                f"draws differed by up to {EARLIER_VAL_SPREAD:g} points in val AP and {EARLIER_HEADLINE_SPREAD:g} "
                "in the SOTIF headline.")
    spread = {key: max(((r["max"] - r["min"]) for r in (mean_range(get(d)) for d in draws.values())
                        if not np.isnan(r["mean"])), default=np.nan)
              for key, get in (("val", lambda ds: [val_ap(x) for x in ds]),
                               ("headline", lambda ds: [(x.get("headline") or {}).get("3d", {}).get("0.7") for x in ds]))}
    return (f"Each model was trained {k} times (training draws); the tables show draw 0, the draws table and the "
            f"models table their means and ranges: a draw moved val AP by up to {spread['val']:.1f} points and "
            f"the SOTIF headline by up to {spread['headline']:.1f} in this run.")


def with_draw_ranges(overview: pd.DataFrame, summary: dict) -> pd.DataFrame:
    """The models table with, for a run of several draws, the mean and range of val AP and headline over
    the draws beside draw 0's figures."""
    draws = summary.get("draws") or {}
    if not draws or overview.empty:
        return overview
    out = overview.copy()
    for col, get in (("val AP3D mod", val_ap), ("AP3D", lambda d: (d.get("headline") or {}).get("3d", {}).get("0.7"))):
        ranges = {m: mean_range([get(d) for d in ds]) for m, ds in draws.items()}
        at = list(out.columns).index(col) + 1
        out.insert(at, f"{col} draws", [_range_text(ranges.get(m)) for m in out["model"]])
    return out


def _range_text(r: dict | None) -> str | None:
    if not r or np.isnan(r["mean"]):
        return None
    return f"{r['mean']:.1f} ({r['min']:.1f}-{r['max']:.1f})"


def forest_figure(pairs: pd.DataFrame) -> Figure:
    """One panel per metric: each pair's mean difference (model_a - model_b) with its 95 % interval; filled
    markers for pairs apart."""
    metrics = list(dict.fromkeys(pairs["metric"]))
    n_rows = max((pairs["metric"] == m).sum() for m in metrics)
    fig = Figure(figsize=(5.0 * len(metrics), 1.2 + 0.28 * n_rows), layout="constrained")
    for k, metric in enumerate(metrics):
        ax = fig.add_subplot(1, len(metrics), k + 1)
        rows = pairs[pairs["metric"] == metric].reset_index(drop=True)
        ys = np.arange(len(rows))[::-1]
        for y, r in zip(ys, rows.itertuples(index=False)):
            c = colour(0) if r.apart else "#7f7f7f"
            ax.plot([r.ci_lo, r.ci_hi], [y, y], color=c, lw=2)
            ax.plot([r.mean_diff], [y], "o", color=c, mfc=c if r.apart else "white")
        ax.axvline(0.0, color="black", lw=0.8)
        ax.set_yticks(ys, [f"{r.model_a} - {r.model_b}" for r in rows.itertuples(index=False)], fontsize=8)
        ax.set(xlabel="difference (AP points)", title=f"{METRIC_NAMES.get(metric, metric)}\n{rows['data'].iloc[0]}")
        ax.title.set_fontsize(9)
        ax.grid(True, axis="x", alpha=0.3)
    return fig


def figure_specs(t: dict) -> dict:
    """``{"pairs": (caption, Figure)}`` when the run has paired comparisons."""
    if "pairs" not in t:
        return {}
    return {"pairs": ("Paired differences between models (model_a - model_b) with 95 % intervals from a paired "
                      "bootstrap over frames (or scenario instances) and training draws; filled: apart.",
                      forest_figure(t["pairs"]))}


def _units(pairs: pd.DataFrame) -> str:
    """"the 300 frames (val AP) and the 42 instances (SOTIF headline)": what each metric's interval resamples."""
    short = {"val_ap3d_moderate": "val AP", "headline_ap3d": "SOTIF headline"}
    rows = pairs.drop_duplicates("metric")
    return " and ".join(f"the {int(r.n_units)} {r.unit}s ({short.get(r.metric, r.metric)})" for r in rows.itertuples())


def sections(t: dict, summary: dict) -> list[tuple]:
    """(key, title, intro, tables, figures) of the pairs and proposals sections the run has."""
    out = []
    if "pairs" in t:
        p = t["pairs"]
        n_boot, _ = bootstrap_settings(summary)
        out.append(("pairs", "Which differences hold: paired comparisons",
                    f"For every two models the difference of val AP (AP40 3D moderate @0.7 on the val set) and of "
                    f"the SOTIF headline (AP40 3D @0.7, filters off, all distances, test split), with a 95 % "
                    f"interval from {n_boot} bootstrap replicates; each replicate draws a training draw per model, "
                    f"then resamples {_units(p)}, the same for both models. "
                    f"{int(p['apart'].sum())} of {len(p)} comparisons are apart. {draws_note(summary)}",
                    [("", p, 1)], ["pairs"]))
    if "proposals" in t:
        out.append(("proposals", "Two-stage models: proposals alone against final boxes",
                    "The AP of each two-stage model's stage-1 proposals (its `rois/` result files) scored as "
                    "detections, next to the AP of its final boxes, on the val set and on the SOTIF test split "
                    f"(means over the draws). {draws_note(summary)}", [("", t["proposals"], 1)], []))
    return out
