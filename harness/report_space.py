"""The report's "SOTIF over the scenario space" section: tables and figures from ``results.json``'s
``sotif_space`` and ``calibration`` entries (``harness.run_space``); nothing is recomputed here
but the grouping of instance verdicts into pass rates (``harness.sotif_space.pass_rates``).

Tables (``tables/<name>.csv``): ``sotif_instances`` (one row per model, set and instance),
``sotif_pass_rates`` (per model, set, condition column and bin: n instances, passes, rate, Wilson
95 % interval, too_few), ``triggering_conditions`` (per model the swept condition bins with the
lowest pass rate), ``sotif_boundary`` (per model and map the slow-car frames and hits per
(condition, distance) cell) and ``calibration`` (per model, IoU and weather class: boxes and ECE).
"""
from __future__ import annotations

import re

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from harness import figures
from harness.sotif_space import AXIS_COLUMNS, CONDITION_COLUMNS, MIN_INSTANCES, boundary_grid, pass_rates

N_TRIGGERING = 5  # bins per model in the triggering-conditions table
DISTANCE_EDGES = np.arange(0.0, 110.0, 10.0)  # m, the boundary maps' distance bins
BOUNDARY_MAPS = {  # map name -> (frame column, bin edges, axis label)
    "rain": ("rain_rate_mmh", [0.0, 1.0, 5.0, 10.0, 25.0, 50.0, 101.0], "rain rate (mm/h)"),
    "fog": ("fog_mor_m", [0.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, np.inf], "fog visibility MOR (m); last: none"),
    "reflectance": ("sc_slow_reflectance", [0.0, 0.05, 0.1, 0.2, 0.4, 0.6, 1.0001], "slow car reflectance at 905 nm"),
}
HOW_TO_READ = ("The maps show where each detector stops finding the slow car (dark cells); the triggering "
               "conditions list the condition bins where it fails most, those with fewer than "
               f"{MIN_INSTANCES} feasible instances marked too few to judge.")


ANSWER_HOW_TO_READ = ("Read down a model's column: a cell is the scenario instances in which it confirmed the "
                      "slow car in time to brake, of those an ideal detector passes; where the passes fall (heavy "
                      "rain, thick fog, a van or truck, dark paint) it stops being safe. A bin with fewer than "
                      f"{MIN_INSTANCES} feasible instances is too few to judge.")


def _instance_counts(inst: pd.DataFrame) -> str:
    """"sotif: 42 instances, sweep: 30 instances" of the instances table."""
    return ", ".join(f"{s}: {g['instance_key'].nunique()} instances" for s, g in inst.groupby("set", sort=False))


def answer_intro(t: dict) -> str:
    """The lead table's text: what a cell is and where the rest of the section is."""
    inst = t["sotif_instances"]
    counts = _instance_counts(inst)
    return (f"Scenario instances ({counts}) passed per model: the slow car confirmed (3 hits in 5 consecutive "
            "frames) with the braking margin, latency included, >= 0. The SOTIF set is the 21 presets with their "
            "instances pooled by precipitation; the sweep set moves one weather axis per instance and draws the "
            "scenario too. Rule, intervals, maps and the triggering conditions: \"SOTIF over the scenario "
            "space\" below.")


def _views(summary: dict):
    for name, m in summary["models"].items():
        for data_set, view in (m.get("sotif_space") or {}).items():
            yield name, data_set, view


def instances_table(summary: dict) -> pd.DataFrame:
    """One row per model, data set and instance (``harness.sotif_space.instance_view`` rows)."""
    rows = [{"model": n, "set": s, **r} for n, s, v in _views(summary) for r in v["instances"]]
    return pd.DataFrame(rows)


def _axis_rows(g: pd.DataFrame, column: str) -> pd.DataFrame:
    """A sweep set's instances of the axis that sweeps ``column`` (the others hold it at its base value)."""
    axis = next((a for a, c in AXIS_COLUMNS.items() if c == column), None)
    if axis is None or "sweep_axis" not in g.columns or g["sweep_axis"].isna().all():
        return g
    return g[g["sweep_axis"] == axis]


def pass_rate_table(instances: pd.DataFrame) -> pd.DataFrame:
    """Pass rates per model, set and condition (the weather and every swept condition column present),
    over feasible instances (``harness.sotif_space.pass_rates``); a sweep axis's column over that axis's
    instances."""
    if instances.empty:
        return pd.DataFrame()
    judged = instances[instances["pass"].notna()]
    parts = [pass_rates(_axis_rows(g, c), c).assign(model=m, set=s)
             for (m, s), g in judged.groupby(["model", "set"], sort=False)
             for c in ("weather", *CONDITION_COLUMNS) if c in g.columns]
    df = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
    return df[["model", "set", *[c for c in df.columns if c not in ("model", "set")]]] if not df.empty else df


RATE_ROWS = {"sotif": ("precipitation_class",),
             "sweep": ("weather", *AXIS_COLUMNS.values(), "sc_slow_body", "sc_slow_paint")}
COLUMN_LABELS = {"weather": "all instances", "precipitation_class": "precipitation", "rain_rate_mmh": "rain (mm/h)",
                 "fog_mor_m": "fog visibility (m)", "road_water": "road water (share)", "sc_slow_body": "slow vehicle",
                 "sc_slow_paint": "slow vehicle paint"}


def rate_matrix(rates: pd.DataFrame) -> pd.DataFrame:
    """The report's pass-rate table: one row per set and condition bin (the SOTIF set by precipitation
    class, the sweep set whole, by each axis and by the slow vehicle's body and paint), one column per model, cells "passed / feasible (rate)";
    ``n_infeasible`` counts the instances no detector could pass. The presets one by one (two instances
    each in the default run) stay in tables/sotif_pass_rates.csv."""
    if rates.empty:
        return pd.DataFrame()
    keep = pd.concat([rates[(rates["set"] == s) & rates["column"].isin(cols)] for s, cols in RATE_ROWS.items()])
    if keep.empty:
        return pd.DataFrame()
    keep = keep.assign(cell=[f"{int(r.n_pass)}/{int(r.n)}" + (f" ({r.rate:.2f})" if r.n else "") for r in keep.itertuples()],
                       condition=[f"{COLUMN_LABELS.get(c, c)}: {b}" if c != "weather" else "all instances"
                                  for c, b in zip(keep["column"], keep["bin"])])
    index = ["set", "condition"]
    wide = keep.pivot_table(index=index, columns="model", values="cell", aggfunc="first", sort=False)
    infeasible = keep.groupby(index, sort=False)["n_infeasible"].max()
    wide = wide[[m for m in dict.fromkeys(keep["model"])]].assign(n_infeasible=infeasible)
    return wide.rename_axis(columns=None).reset_index()  # no 'model' axis name over the index


def triggering_table(rates: pd.DataFrame, per_model: int = N_TRIGGERING) -> pd.DataFrame:
    """Per model the swept condition bins (not the weather preset) with the lowest pass rate; bins with
    enough instances first, those with fewer than ``MIN_INSTANCES`` marked "too few to judge"."""
    if rates.empty:
        return pd.DataFrame()
    df = rates[rates["column"] != "weather"].copy()
    df["judgement"] = np.where(df["too_few"], f"too few to judge (< {MIN_INSTANCES})", "")
    df = df.sort_values(["model", "too_few", "rate", "n"], ascending=[True, True, True, False], kind="stable")
    order = {m: i for i, m in enumerate(dict.fromkeys(rates["model"]))}
    df = df.groupby("model", sort=False).head(per_model)
    return df.sort_values("model", key=lambda c: c.map(order), kind="stable").reset_index(drop=True)


def frames_table(summary: dict) -> pd.DataFrame:
    parts = [pd.DataFrame(v["frames"]).assign(model=n, set=s) for n, s, v in _views(summary) if v.get("frames")]
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()


def boundary_table(frames: pd.DataFrame) -> pd.DataFrame:
    """Per model and map: slow-car frames (n) and hits per (condition bin, distance bin) cell, both sets."""
    rows = []
    for model, g in frames.groupby("model", sort=False) if not frames.empty else []:
        for name, (col, edges, _) in BOUNDARY_MAPS.items():
            if col not in g.columns or g[col].isna().all():
                continue
            hits, counts = boundary_grid(_mapped(g, col), col, DISTANCE_EDGES, edges)
            for i in range(counts.shape[0]):
                for j in range(counts.shape[1]):
                    rows.append({"model": model, "map": name, "condition_lo": edges[i], "condition_hi": edges[i + 1],
                                 "distance_lo_m": DISTANCE_EDGES[j], "distance_hi_m": DISTANCE_EDGES[j + 1],
                                 "n": int(counts[i, j]), "hits": int(hits[i, j]),
                                 "p_detect": hits[i, j] / counts[i, j] if counts[i, j] else np.nan})
    return pd.DataFrame(rows)


def _mapped(frames: pd.DataFrame, col: str) -> pd.DataFrame:
    """Fog MOR 0 (no fog) goes into the last, open-ended bin."""
    if col != "fog_mor_m":
        return frames
    return frames.assign(fog_mor_m=frames[col].replace(0.0, 1e9))


def calibration_table(summary: dict) -> pd.DataFrame:
    rows = [{"model": n, "iou": iou, "weather_class": cls, "n_boxes": r["n"], "ece": r["ece"]}
            for n, m in summary["models"].items() for iou, by in (m.get("calibration") or {}).items()
            for cls, r in by.items()]
    return pd.DataFrame(rows)


def build(summary: dict) -> dict[str, pd.DataFrame]:
    """The section's tables by name (empty when the run has no scenario-space results)."""
    inst = instances_table(summary)
    rates = pass_rate_table(inst)
    return {"sotif_instances": inst, "sotif_pass_rates": rates, "triggering_conditions": triggering_table(rates),
            "sotif_boundary": boundary_table(frames_table(summary)), "calibration": calibration_table(summary)}


# ----------------------------------------------------------------------------- figures
def margin_figure(inst: pd.DataFrame) -> Figure:
    """Per model a strip of braking margins (m) by precipitation class; never-confirmed instances drawn
    at the bottom edge as crosses."""
    models = list(dict.fromkeys(inst["model"]))
    fig = Figure(figsize=(3.2 * len(models), 3.2))
    classes = sorted(inst["precipitation_class"].dropna().astype(str).unique()) if "precipitation_class" in inst \
        else ["all"]
    floor = float(np.nanmin(inst["margin_m"].astype(float))) - 5 if inst["margin_m"].notna().any() else -5.0
    for k, model in enumerate(models):
        ax = fig.add_subplot(1, len(models), k + 1)
        g = inst[inst["model"] == model]
        for i, cls in enumerate(classes):
            c = g if cls == "all" else g[g["precipitation_class"].astype(str) == cls]
            m = c["margin_m"].astype(float).to_numpy()
            x = i + np.linspace(-0.2, 0.2, len(m)) if len(m) > 1 else np.full(len(m), float(i))
            ok = ~np.isnan(m)
            ax.scatter(x[ok], m[ok], s=10, color=figures.colour(k))
            ax.scatter(x[~ok], np.full((~ok).sum(), floor), s=14, marker="x", color="black")
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set_xticks(range(len(classes)), classes)
        ax.set_title(model, fontsize=9)
        ax.set_ylabel("braking margin (m)" if k == 0 else "")
    fig.tight_layout()
    return fig


def boundary_figure(boundary: pd.DataFrame, model: str) -> Figure:
    """One model's detection probability of the slow car per (distance, condition) cell; empty cells blank."""
    maps = [m for m in BOUNDARY_MAPS if (boundary["map"] == m).any()]
    fig = Figure(figsize=(4.0 * len(maps), 3.2))
    for k, name in enumerate(maps):
        col, edges, label = BOUNDARY_MAPS[name]
        g = boundary[(boundary["model"] == model) & (boundary["map"] == name)]
        grid = g["p_detect"].to_numpy(float).reshape(len(edges) - 1, len(DISTANCE_EDGES) - 1)
        ax = fig.add_subplot(1, len(maps), k + 1)
        im = ax.imshow(np.ma.masked_invalid(grid), origin="lower", aspect="auto", vmin=0, vmax=1, cmap="viridis")
        ax.set_xticks(range(len(DISTANCE_EDGES) - 1), [f"{d:.0f}" for d in DISTANCE_EDGES[:-1]], fontsize=7)
        ax.set_yticks(range(len(edges) - 1), [f"{e:g}" for e in edges[:-1]], fontsize=7)
        ax.set_xlabel("distance to the slow car (m, bin start)")
        ax.set_ylabel(label + ", bin start", fontsize=8)
        fig.colorbar(im, ax=ax, label="P(detected)")
    fig.suptitle(model)
    fig.tight_layout()
    return fig


def reliability_figure(summary: dict, iou: str = "0.7") -> Figure:
    """Per model: accuracy against mean score per score bin, one line per weather class."""
    models = [n for n, m in summary["models"].items() if (m.get("calibration") or {}).get(iou)]
    fig = Figure(figsize=(3.0 * len(models), 3.0))
    for k, model in enumerate(models):
        ax = fig.add_subplot(1, len(models), k + 1)
        ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--")
        for i, (cls, r) in enumerate(summary["models"][model]["calibration"][iou].items()):
            pts = [(c, a) for c, a in zip(r["bins"]["confidence"], r["bins"]["accuracy"]) if c is not None]
            if pts:
                ax.plot(*zip(*pts), marker="o", ms=3, color=figures.colour(i),
                        label=f"{cls} (ECE {r['ece']:.3f})")
        ax.set_title(model, fontsize=9)
        ax.set_xlabel("mean score")
        ax.set_ylabel(f"share matched at 3D IoU {iou}" if k == 0 else "")
        ax.legend(fontsize=6)
    fig.tight_layout()
    return fig


def figure_specs(summary: dict, t: dict) -> dict:
    """``{name: (caption, Figure)}`` of the section."""
    specs = {}
    inst = t.get("sotif_instances", pd.DataFrame())
    if not inst.empty and "margin_m" in inst:
        specs["sotif_margins"] = ("Braking margin per instance (m; >= 0 passes), by precipitation class; crosses: "
                                  "never confirmed.", margin_figure(inst))
    boundary = t.get("sotif_boundary", pd.DataFrame())
    for model in dict.fromkeys(boundary["model"]) if not boundary.empty else []:
        specs[f"boundary_{model}"] = (f"{model}: share of slow-car frames after the lane change detected (SOTIF and "
                                      "sweep sets; score >= operating threshold, BEV "
                                      "IoU >= 0.5) per distance and condition bin; blank cells hold no frame "
                                      "(counts in tables/sotif_boundary.csv).", boundary_figure(boundary, model))
    if not t.get("calibration", pd.DataFrame()).empty:
        specs["reliability"] = ("Reliability diagrams: share of boxes matched at 3D IoU 0.7 against mean score per "
                                "score bin (10 equal-width bins), per weather class.", reliability_figure(summary))
    return specs


def ci_method(results: dict) -> str:
    """How the per-weather intervals were made (the evaluation's ``ci_method``; older results: over frames)."""
    for res in results.values():
        for row in ((res.get("groups_by") or {}).get("weather") or {}).get("rows", {}).values():
            if row.get("ci_method"):
                return row["ci_method"] + _few_clusters(row["ci_method"])
    return "bootstrap over frames"


def _few_clusters(method: str) -> str:
    """A caveat when an interval over instances rests on fewer than ``MIN_INSTANCES`` of them."""
    found = re.search(r"over instances \((\d+) instances", method)
    if not found or int(found.group(1)) >= MIN_INSTANCES:
        return ""
    n = int(found.group(1))
    return (f"; with {n} instances per preset such an interval is the spread of {n} drives, not a 95% interval: "
            "compare presets by the pass rates and rain classes below, which pool instances")


def section_intro(summary: dict, t: dict) -> str:
    """The section's text: the rule, the latency, the interval method and the instance counts."""
    inst = t["sotif_instances"]
    rule = next((v["rule"] for _, _, v in _views(summary)), {"k": 3, "n": 5})
    counts = _instance_counts(inst)
    return (f"Per scenario instance ({counts}): the slow car counts as found at the first frame that closes "
            f"{rule['n']} consecutive frames (at or after the lane change) holding {rule['k']} hits (score >= the "
            "model's operating threshold, BEV IoU >= 0.5). The braking margin is the gap left at that frame, had "
            "the ego held its closing speed from the lane change, minus the stopping distance with the model's "
            "onnxruntime latency (p50) added to the reaction time; an instance passes when the margin is >= 0. "
            "An instance is feasible when an ideal detector (a hit in every frame where the slow car is labelled, "
            "no latency) passes it; infeasible ones leave no room to brake whatever the detector, so rates count "
            "feasible instances only and the table names how many were left out. The sweep set moves one weather "
            "axis per instance (rain rate, fog visibility or road water) and draws the scenario parameters too; "
            f"each axis is split into bins of at least {MIN_INSTANCES} instances. Pass rates carry a 95% Wilson "
            "score interval over instances (tables/sotif_pass_rates.csv, with every preset and scenario parameter); "
            f"a bin with fewer than {MIN_INSTANCES} is too few to judge. Calibration: expected "
            "calibration error of the scores against a match at 3D IoU 0.7 / 0.5, 10 equal-width bins.")
