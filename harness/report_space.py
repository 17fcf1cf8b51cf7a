"""The report's "SOTIF over the scenario space" section: tables and figures from ``results.json``'s
``sotif_space`` (``harness.verdict``, written by ``harness.run_space``) and ``calibration`` entries; nothing is
recomputed here but the grouping of instance verdicts into pass rates (``harness.sotif_space.pass_rates``).

Tables (``tables/<name>.csv``): ``sotif_instances`` (one row per model, set, instance and verdict: perception or
system), ``sotif_pass_rates`` (per model, set, verdict, body class, condition column and bin: preventable
instances, passes, rate, Wilson 95 % interval over instances, too_few, unpreventable ones), ``sotif_phantoms``
(per model, set and weather: phantom in-path boxes and events per hour), ``sotif_pairs`` (per set, verdict and
pair of models: exact McNemar on the verdicts, paired bootstrap on the median a_req; ``harness.verdict_pairs``),
``triggering_conditions`` (per model
the car-bodied condition bins with the lowest perception pass rate), ``sotif_boundary`` (per model and map the
judged frames and in-path hits per (condition, distance) cell) and ``calibration`` (per model, IoU and weather
class: boxes and ECE).
"""
from __future__ import annotations

import re

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from harness import figures
from harness.sotif_space import MIN_INSTANCES, boundary_grid, pass_rates
from harness.verdict_pairs import pair_table

N_TRIGGERING = 5  # bins per model in the triggering-conditions table
HEADLINE, APART = "car", "outside the learned classes"  # harness.reference.body_class
AXIS_COLUMNS = {"rain": "rain_mm_h", "fog": "fog_mor_m", "water": "water"}  # sweep axis -> its instance column
CONDITIONS = ("precipitation_class", *AXIS_COLUMNS.values(), "reflectance", "body", "paint")
DISTANCE_EDGES = np.arange(0.0, 110.0, 10.0)  # m, the boundary maps' distance bins
BOUNDARY_MAPS = {  # map name -> (frame column, bin edges, axis label)
    "rain": ("rain_rate_mmh", [0.0, 1.0, 5.0, 10.0, 25.0, 50.0, 101.0], "rain rate (mm/h)"),
    "fog": ("fog_mor_m", [0.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, np.inf], "fog visibility MOR (m); last: none"),
    "reflectance": ("sc_slow_reflectance", [0.0, 0.05, 0.1, 0.2, 0.4, 0.6, 1.0001], "slow car reflectance at 905 nm"),
}
HOW_TO_READ = ("The maps show where each detector stops finding the slow vehicle in its path (dark cells); the "
               "triggering conditions list the car-bodied condition bins where it fails most, those with fewer than "
               f"{MIN_INSTANCES} preventable instances marked too few to judge.")


ANSWER_HOW_TO_READ = ("Read down a model's column: a rate cell is the car-bodied instances in which it confirmed "
                      "the slow vehicle in time to stop at <= 6 m/s^2, of those a reference perception could "
                      "(preventable), with the rate and its 95 % interval over instances; where the passes fall (heavy "
                      "rain, thick fog, dark paint) it stops being safe. Vans and trucks, outside the class the "
                      "detectors learned, have their own row, as have the system verdict (latency included) and "
                      f"phantom in-path boxes. A bin with fewer than {MIN_INSTANCES} preventable instances is too few "
                      "to judge.")


def _instance_counts(inst: pd.DataFrame) -> str:
    """"sotif: 42 instances, sweep: 30 instances" of the instances table."""
    return ", ".join(f"{s}: {g['instance'].nunique()} instances" for s, g in inst.groupby("set", sort=False))


def answer_intro(t: dict, bounds: bool = False) -> str:
    """The lead table's text: what a cell is and where the rest of the section is; with ``bounds``, what the
    boundary rows are (``harness.report_bounds``)."""
    counts = _instance_counts(t["sotif_instances"])
    lead = ("The bounds rows come first: per reference scenario (ego and slow car km/h, body, paint) and axis, all "
            "else held at the reference, where the model's perception verdict flips from pass to fail, failing above "
            "the bracket in rain and road water and below it in fog visibility and reflectance (plan and tolerances "
            "under the boundaries table below). ") if bounds else ""
    return (f"{lead}Scenario instances ({counts}) passed per model: the slow vehicle confirmed (3 in-path hits within "
            "0.5 s) early enough that, after an automated system's 0.35 s reaction, stopping 2 m short of it needs at "
            "most 6 m/s^2 (UN R157), counted over the instances a reference perception passes. The SOTIF set is the "
            "21 presets with their instances pooled by precipitation (copies of the same drives under 21 skies); "
            "the sweep set moves one weather axis per instance and draws the scenario too. Rule, reference, "
            "intervals, maps and the triggering conditions: \"SOTIF over the scenario space\" below.")


def _views(summary: dict):
    for name, m in summary["models"].items():
        for data_set, view in (m.get("sotif_space") or {}).items():
            yield name, data_set, view


def instances_table(summary: dict) -> pd.DataFrame:
    """One row per model, data set, instance and verdict (``harness.verdict`` rows)."""
    rows = [{**r, "model": n, "set": s} for n, s, v in _views(summary) for r in v.get("instances", [])]
    df = pd.DataFrame(rows)
    return df[["model", "set", *[c for c in df.columns if c not in ("model", "set")]]] if not df.empty else df


def phantom_table(summary: dict) -> pd.DataFrame:
    """One row per model, data set and weather: phantom in-path boxes and events per hour."""
    rows = [{"set": s, **r, "model": n} for n, s, v in _views(summary) for r in v.get("phantoms", [])]
    df = pd.DataFrame(rows)
    return df[["model", "set", *[c for c in df.columns if c not in ("model", "set")]]] if not df.empty else df


def _axis_rows(g: pd.DataFrame, column: str) -> pd.DataFrame:
    """A sweep set's instances of the axis that sweeps ``column`` (the others hold it at its base value)."""
    axis = next((a for a, c in AXIS_COLUMNS.items() if c == column), None)
    if axis is None or "sweep_axis" not in g.columns or g["sweep_axis"].isna().all():
        return g
    return g[g["sweep_axis"] == axis]


def pass_rate_table(instances: pd.DataFrame) -> pd.DataFrame:
    """Pass rates per model, set, verdict, body class and condition (all instances, then every condition column
    present), over preventable instances (``harness.sotif_space.pass_rates``); a sweep axis's column over that
    axis's instances."""
    if instances.empty:
        return pd.DataFrame()
    df = instances.assign(all="all", feasible=instances["preventable"].astype(bool),
                          **{"pass": instances["passed"].astype(bool)})
    parts = [pass_rates(_axis_rows(g, c), c).assign(model=m, set=s, verdict=v, body_class=b)
             for (m, s, v, b), g in df.groupby(["model", "set", "verdict", "body_class"], sort=False)
             for c in ("all", *CONDITIONS) if c in g.columns]
    out = pd.concat([p for p in parts if not p.empty], ignore_index=True) if parts else pd.DataFrame()
    if out.empty:
        return out
    out = out.rename(columns={"n_infeasible": "n_unpreventable"})
    return out[["model", "set", "verdict", "body_class", *[c for c in out.columns
                                                           if c not in ("model", "set", "verdict", "body_class")]]]


RATE_ROWS = {"sotif": ("all", "precipitation_class"), "sweep": ("all", *AXIS_COLUMNS.values(), "paint")}
COLUMN_LABELS = {"precipitation_class": "precipitation", "rain_mm_h": "rain (mm/h)", "fog_mor_m": "fog visibility (m)",
                 "water": "road water (share)", "paint": "slow vehicle paint"}


def _cell(r) -> str:
    if not r.n:
        return "0/0"
    return f"{int(r.n_pass)}/{int(r.n)} ({r.rate:.2f}; {r.lo:.2f}-{r.hi:.2f})"


def _matrix_rows(rates: pd.DataFrame) -> pd.DataFrame:
    """The rows of the lead table: per set the car-bodied perception rows, vans and trucks, the system verdict."""
    parts = []
    for s, cols in RATE_ROWS.items():
        r = rates[rates["set"] == s]
        car = r[(r["verdict"] == "perception") & (r["body_class"] == HEADLINE) & r["column"].isin(cols)]
        parts.append(car.assign(condition=[f"car-bodied: {COLUMN_LABELS.get(c, c)} {b}" if c != "all"
                                           else "car-bodied: all" for c, b in zip(car["column"], car["bin"])]))
        apart = r[(r["verdict"] == "perception") & (r["body_class"] == APART) & (r["column"] == "all")]
        parts.append(apart.assign(condition="vans and trucks (outside the learned classes)"))
        system = r[(r["verdict"] == "system") & (r["body_class"] == HEADLINE) & (r["column"] == "all")]
        parts.append(system.assign(condition="car-bodied, system verdict (latency p90 on this machine)"))
    return pd.concat(parts, ignore_index=True)


def rate_matrix(rates: pd.DataFrame, phantoms: pd.DataFrame | None = None) -> pd.DataFrame:
    """The report's SOTIF table: one row per set and condition (module docstring), one column per model, cells
    "passed/preventable (rate; Wilson 95 % interval over instances)"; ``unpreventable``: the instances no
    detector is asked to pass (the reference could not); a last row per set: phantom in-path boxes per hour."""
    if rates.empty:
        return pd.DataFrame()
    keep = _matrix_rows(rates)
    if keep.empty:
        return pd.DataFrame()
    keep = keep.assign(cell=[_cell(r) for r in keep.itertuples()])
    index = ["set", "condition"]
    wide = keep.pivot_table(index=index, columns="model", values="cell", aggfunc="first")
    unprev = keep.groupby(index)["n_unpreventable"].max().astype("Int64")
    order = pd.MultiIndex.from_frame(keep[index].drop_duplicates())  # the rows as _matrix_rows made them
    wide = wide[[m for m in dict.fromkeys(keep["model"])]].assign(unpreventable=unprev).reindex(order)
    wide = wide.rename_axis(columns=None).reset_index()  # no 'model' axis name over the index
    out = pd.concat([wide, _phantom_rows(phantoms, list(dict.fromkeys(keep["model"])))], ignore_index=True)
    out["unpreventable"] = [("–" if pd.isna(v) else str(int(v))) for v in out["unpreventable"]]
    sets = {s: i for i, s in enumerate(dict.fromkeys(out["set"]))}
    return out.sort_values("set", key=lambda c: c.map(sets), kind="stable").reset_index(drop=True)


def _phantom_rows(phantoms: pd.DataFrame | None, models: list) -> pd.DataFrame:
    """Per set: phantom in-path boxes per hour over all its frames, per model."""
    if phantoms is None or phantoms.empty:
        return pd.DataFrame()
    rows = []
    for s, g in phantoms.groupby("set", sort=False):
        row = {"set": s, "condition": "phantom in-path boxes per hour (all weathers)"}
        for m, gm in g.groupby("model", sort=False):
            hours = gm["hours"].sum()
            row[m] = f"{gm['n_false'].sum() / hours:.0f}/h ({int(gm['n_false'].sum())} in {hours:.3g} h)" if hours else "-"
        rows.append(row)
    return pd.DataFrame(rows, columns=["set", "condition", *models])


def triggering_table(rates: pd.DataFrame, per_model: int = N_TRIGGERING) -> pd.DataFrame:
    """Per model the car-bodied condition bins (not all instances, not the weather preset) with the lowest
    perception pass rate; bins with enough instances first, those with fewer than ``MIN_INSTANCES`` marked "too
    few to judge"."""
    if rates.empty:
        return pd.DataFrame()
    df = rates[(rates["verdict"] == "perception") & (rates["body_class"] == HEADLINE) & (rates["column"] != "all")].copy()
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
    pairs = pair_table(inst) if not inst.empty and inst["model"].nunique() > 1 else pd.DataFrame()
    return {"sotif_instances": inst, "sotif_pass_rates": rates, "sotif_phantoms": phantom_table(summary),
            "sotif_pairs": pairs,
            "triggering_conditions": triggering_table(rates), "sotif_boundary": boundary_table(frames_table(summary)),
            "calibration": calibration_table(summary)}


# ----------------------------------------------------------------------------- figures
def margin_figure(inst: pd.DataFrame) -> Figure:
    """Per model a strip of the perception verdict's margins at 6 m/s^2 (m) over the preventable instances, by
    precipitation class; never-confirmed instances drawn at the bottom edge as crosses."""
    inst = inst[(inst["verdict"] == "perception") & inst["preventable"].astype(bool)]
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
        ax.set_ylabel("margin at 6 m/s^2 (m)" if k == 0 else "")
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
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
        else:  # every score bin empty (a model with no detection): say so instead of an empty legend
            ax.text(0.5, 0.5, "no scored detection", ha="center", va="center", transform=ax.transAxes, fontsize=8)
    fig.tight_layout()
    return fig


def figure_specs(summary: dict, t: dict) -> dict:
    """``{name: (caption, Figure)}`` of the section."""
    specs = {}
    inst = t.get("sotif_instances", pd.DataFrame())
    if not inst.empty and "margin_m" in inst and inst["preventable"].astype(bool).any():
        specs["sotif_margins"] = ("Perception verdict per preventable instance: metres to spare when braking at "
                                  "6 m/s^2 from the decision (>= 0 passes), by precipitation class; crosses: never "
                                  "confirmed.", margin_figure(inst))
    boundary = t.get("sotif_boundary", pd.DataFrame())
    for model in dict.fromkeys(boundary["model"]) if not boundary.empty else []:
        specs[f"boundary_{model}"] = (f"{model}: share of the slow vehicle's frames after the lane change with an "
                                      "in-path hit (SOTIF and sweep sets; score >= operating threshold) per distance "
                                      "and condition bin, hidden frames included; blank cells hold no frame (counts "
                                      "in tables/sotif_boundary.csv).", boundary_figure(boundary, model))
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
    """The section's text: the hit, the reference, the rule, the outcome, the intervals and the instance counts."""
    inst = t["sotif_instances"]
    rule = next((v["rule"] for _, _, v in _views(summary)), {"k": 3, "window_s": 0.5, "reaction_s": 0.35})
    counts = _instance_counts(inst)
    return (f"Per scenario instance ({counts}), from the lane change on, frames at the LiDAR's 10 Hz. A frame is an "
            "in-path hit when a box of the model (score >= its operating threshold) lies on the slow vehicle (BEV "
            "footprints overlap or centres within 2 m) with its rear face within max(1 m, 3 % of the range) of the "
            f"true one. The slow vehicle is confirmed at the first hit that closes {rule['k']} hits within "
            f"{rule['window_s']:g} s. The reference confirms it by the same rule over the frames in which >= 30 % of "
            "its footprint is unoccluded from the sensor and within 80 m (geometry, whatever the weather); an "
            "instance is preventable when, after the reference's confirmation and a reaction of "
            f"{rule['reaction_s']:g} s, stopping 2 m short (the ego holding its closing speed until then) needs at "
            "most 6 m/s^2. Unpreventable instances carry their reason (occlusion, range, kinematics) in "
            "tables/sotif_instances.csv and count against no model. A model's perception verdict uses every frame; "
            "its system verdict the frames it can process at its onnxruntime latency p90 on this machine, the "
            "latency added to the decision. delay_s is its decision behind the reference's confirmation. Rates count "
            "preventable instances, car-bodied apart from vans and trucks (outside the class the detectors learned), "
            f"each axis split into bins of at least {MIN_INSTANCES} instances, with a 95% Wilson score interval over "
            "instances: the SOTIF set's instances are 21 weather copies of each drive (ClearNoon#1 and HardRainNight#1 "
            "are one drive), so its interval over-counts the evidence. Phantom braking: boxes in the ego's lane "
            "corridor that lie on no object, per hour of judged frames (tables/sotif_phantoms.csv). Two models differ on "
            "an instance set only where an exact McNemar test on their paired verdicts says so (p < 0.05; "
            "tables/sotif_pairs.csv, with a paired bootstrap over drives or instances on the median a_req). BEV IoU >= 0.5 "
            "stays a box-quality column (box_iou05_share). Calibration: expected calibration error of the scores "
            "against a match at 3D IoU 0.7 / 0.5, 10 equal-width bins.")
