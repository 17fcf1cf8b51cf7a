"""The numbers the documents quote from a sample, computed from its ``tables/*.csv`` with pandas and written as
text (``harness.sample_docs`` lays them out with jinja2). Each public function takes a ``SampleTables`` and
returns the keyword arguments of the template macro of the same name; a table or column it needs and does not
find raises ``MissingTable`` naming the file.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from harness.cells import num, span
from harness.core.kitti import KittiError
from harness.report import MODEL_LABELS

AXES = {"rain": ("rain_rate_mmh", "rain", "mm/h", 1), "fog": ("fog_mor_m", "fog", "m", 0),  # sweep_axis ->
        "water": ("road_water", "water", "", 2)}  # (column, word, unit, decimals)
AXIS_WORDS = {"rain": "rain", "fog": "fog visibility", "water": "road water"}
PAINT = {"nir_black": "NIR-black"}
BODY = {"suv": "SUV"}
RAIN_GRADES = ("soft rain", "mid rain", "hard rain")
CLASSES = ("dry", "wet", "rain")


class MissingTable(KittiError):
    """A table of the sample, or a column of it, that a block needs is not there."""


class SampleTables:
    """The sample's ``tables/<name>.csv``, each read once."""

    def __init__(self, folder):
        self.folder, self._read = Path(folder), {}

    def __call__(self, name: str, columns=()) -> pd.DataFrame:
        path = self.folder / f"{name}.csv"
        if name not in self._read:
            if not path.is_file():
                raise MissingTable(path, "table not found")
            try:
                self._read[name] = pd.read_csv(path, dtype={"frame_id": str})
            except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
                raise KittiError(path, f"not a readable CSV table ({e})") from None
        df = self._read[name]
        missing = [c for c in columns if c not in df.columns]
        if missing:
            raise MissingTable(path, f"no column {', '.join(map(repr, missing))}")
        return df


# ----------------------------------------------------------------------------- formatting
def _same(values, digits: int = 0, sep: str = " / ") -> str:
    """One number when all read the same, else each."""
    texts = [num(v, digits) for v in values]
    return texts[0] if len(set(texts)) == 1 else sep.join(texts)


def _each(values, what: str) -> str:
    """"74 frames each", or "74 / 80 / 74 frames"."""
    text = _same(values)
    return f"{text} {what}" if " / " in text else f"{text} {what} each"


def _true(s: pd.Series) -> pd.Series:
    return s.astype(str).str.strip().str.lower().eq("true")


def _label(model: str) -> str:
    return MODEL_LABELS.get(model, model)


def _vehicle(paint: str, body: str) -> str:
    return f"{PAINT.get(paint, paint)} {BODY.get(body, body)}"


def _table(df: pd.DataFrame, right: set) -> dict:
    """A text table for the ``md_table`` macro: columns, right-aligned flags, rows of strings."""
    return {"columns": list(df.columns), "right": [c in right for c in df.columns],
            "rows": df.astype(str).values.tolist()}


# ----------------------------------------------------------------------------- counts shared by the blocks
def _instances(t: SampleTables, data_set: str) -> pd.DataFrame:
    """The first model's instances of ``data_set`` (feasibility and the scenario are the same for every model)."""
    inst = t("sotif_instances", ["model", "set", "instance_key", "instance", "weather", "pass", "feasible",
                                 "margin_m", "ideal_margin_m"])
    rows = inst[inst["set"] == data_set]
    if rows.empty:
        raise MissingTable(t.folder / "sotif_instances.csv", f"no instance of the {data_set!r} set")
    return rows[rows["model"] == rows["model"].iloc[0]]


def sotif_counts(t: SampleTables) -> dict:
    """The SOTIF test set: presets, instances per preset, frames, cars."""
    by_weather = t("data_by_weather", ["weather", "n_test"])
    detail = t("weather_detail", ["model", "n_car"])
    sotif = _instances(t, "sotif")
    tested = by_weather[by_weather["n_test"] > 0]
    per_preset = sotif.groupby("weather").size()
    return {"presets": len(tested), "per_preset": _same(per_preset.unique()), "instances": len(sotif),
            "frames": num(tested["n_test"].sum()),
            "cars": num(detail[detail["model"] == detail["model"].iloc[0]]["n_car"].sum())}


def _passed(t: SampleTables) -> pd.DataFrame:
    """Per model and set: instances passed, of the feasible ones."""
    inst = t("sotif_instances", ["model", "set", "pass", "feasible"])
    feasible = _true(inst["feasible"])
    inst = inst.assign(ok=_true(inst["pass"]) & feasible, feasible=feasible)
    return inst.groupby(["model", "set"], sort=False).agg(n_pass=("ok", "sum"), n=("feasible", "sum"))


def _rain_rates(t: SampleTables, presets) -> list[str]:
    by_weather = t("data_by_weather", ["weather", "rain_rate_mmh"]).set_index("weather")["rain_rate_mmh"]
    return [f"{by_weather[p]:g}" if p in by_weather.index else "?" for p in presets]


# ----------------------------------------------------------------------------- README
def readme_table(t: SampleTables) -> dict:
    """The README's results table and the counts behind it."""
    ov = t("overview", ["model", "val AP3D mod", "val frames", "AP3D"])
    rain = t("rain", ["model", "iou", "condition", "group", "n_frames", "n_car", "ap"])
    rt = t("runtime", ["model", "ort_p50_ms", "size_mb"]).set_index("model")
    passed = _passed(t)
    r05 = rain[rain["iou"].astype(float) == 0.5]
    ap = r05.pivot_table(index="model", columns="condition", values="ap", aggfunc="first")
    cell = lambda m, conds: " / ".join(num(ap.loc[m, c], 1) if m in ap.index and c in ap.columns and
                                       pd.notna(ap.loc[m, c]) else "–" for c in conds)
    sets = lambda m: " / ".join(f"{int(passed.loc[(m, s), 'n_pass'])}/{int(passed.loc[(m, s), 'n'])}"
                                if (m, s) in passed.index else "–" for s in ("sotif", "sweep"))
    rows = pd.DataFrame({
        "model": [_label(m) for m in ov["model"]], "val": [num(v, 1) for v in ov["val AP3D mod"]],
        "AP @0.7": [num(v, 1) for v in ov["AP3D"]], "AP @0.5 dry / wet / rain": [cell(m, CLASSES) for m in ov["model"]],
        "soft / mid / hard rain": [cell(m, RAIN_GRADES) for m in ov["model"]],
        "SOTIF passed: presets / sweep": [sets(m) for m in ov["model"]],
        "latency": [f"{num(rt.loc[m, 'ort_p50_ms'])} ms" if m in rt.index else "–" for m in ov["model"]],
        "ONNX": [f"{num(rt.loc[m, 'size_mb'], 1)} MB" if m in rt.index else "–" for m in ov["model"]]})
    first = r05[r05["model"] == r05["model"].iloc[0]].set_index("condition")
    sweep = _instances(t, "sweep")
    return {"table": _table(rows, {"val", "AP @0.7", "SOTIF passed: presets / sweep", "latency", "ONNX"}),
            "sotif": sotif_counts(t), "val_frames": _same(ov["val frames"].unique()),
            "class_frames": " / ".join(num(first.loc[c, "n_frames"]) for c in CLASSES),
            "class_cars": " / ".join(num(first.loc[c, "n_car"]) for c in CLASSES),
            "grade_rates": " / ".join(_rain_rates(t, [first.loc[g, "group"] for g in RAIN_GRADES])),
            "grade_frames": _each([first.loc[g, "n_frames"] for g in RAIN_GRADES], "frames"),
            "sweep_instances": len(sweep), "sweep_feasible": int(_true(sweep["feasible"]).sum()),
            "sweep_axes": _axes_words(sweep)}


def _axes_words(sweep: pd.DataFrame) -> str:
    axes = [AXIS_WORDS.get(a, a) for a in dict.fromkeys(sweep["sweep_axis"]) if isinstance(a, str)] \
        if "sweep_axis" in sweep.columns else []
    return ", ".join(axes[:-1]) + f" and {axes[-1]}" if len(axes) > 1 else "".join(axes)


# ----------------------------------------------------------------------------- docs/results.md
def _scenario(row) -> str:
    """"NIR-black SUV, ego 100 km/h, slow car 78 km/h" of an instance row."""
    return (f"{_vehicle(row['sc_slow_paint'], row['sc_slow_body'])}, ego {num(row['sc_ego_speed_kmh'])} km/h, "
            f"slow car {num(row['sc_slow_speed_kmh'])} km/h")


def _drawn(t: SampleTables) -> list[str]:
    """The SOTIF set's drawn drives (instance > 0), each as ``_scenario`` words."""
    sotif = _instances(t, "sotif")
    t("sotif_instances", ["sc_slow_paint", "sc_slow_body", "sc_ego_speed_kmh", "sc_slow_speed_kmh"])
    return [_scenario(g.iloc[0]) for i, g in sotif.groupby("instance") if i > 0]


def data_sets(t: SampleTables) -> dict:
    """The three data sets of the sample: SOTIF, sweep, val."""
    ov = t("overview", ["val frames"])
    sweep = _instances(t, "sweep")
    t("sotif_instances", ["sweep_axis", "sc_ego_speed_kmh", "sc_slow_speed_kmh", *(a[0] for a in AXES.values())])
    per_axis = sweep.groupby("sweep_axis", sort=False).size()
    axes = []
    for axis, rows in sweep.groupby("sweep_axis", sort=False):
        if axis not in AXES:
            axes.append(AXIS_WORDS.get(axis, axis))
            continue
        column, _, unit, digits = AXES[axis]
        axes.append(f"{AXIS_WORDS[axis]} {span(rows[column].min(), rows[column].max(), digits)} {unit}".rstrip())
    return {"sotif": sotif_counts(t), "drawn": _drawn(t), "sweep_instances": len(sweep),
            "per_axis": f"{per_axis.iloc[0]} per weather axis" if per_axis.nunique() == 1 else
            ", ".join(f"{AXIS_WORDS.get(a, a)} {n}" for a, n in per_axis.items()), "axes": axes,
            "ego": span(sweep["sc_ego_speed_kmh"].min(), sweep["sc_ego_speed_kmh"].max()),
            "slow": span(sweep["sc_slow_speed_kmh"].min(), sweep["sc_slow_speed_kmh"].max()),
            "val_frames": _same(ov["val frames"].unique())}


def _condition(row) -> str:
    if row["sweep_axis"] not in AXES:
        return str(row["sweep_axis"])
    column, word, unit, digits = AXES[row["sweep_axis"]]
    return f"{word} {num(row[column], digits)} {unit}".rstrip()


def _margin(v) -> str:
    return "-" if pd.isna(v) else num(v, 1)


def sweep_instances(t: SampleTables) -> dict:
    """One row per sweep instance: its condition, slow vehicle, closing speed, the ideal margin and each model's."""
    inst = t("sotif_instances", ["sweep_axis", "closing_speed_mps", "sc_slow_paint", "sc_slow_body",
                                 *(a[0] for a in AXES.values())])
    sweep = inst[inst["set"] == "sweep"]
    if sweep.empty:
        raise MissingTable(t.folder / "sotif_instances.csv", "no instance of the 'sweep' set")
    first = _instances(t, "sweep").copy()
    first["order"] = [list(AXES).index(a) if a in AXES else len(AXES) for a in first["sweep_axis"]]
    first["value"] = [r[AXES[r["sweep_axis"]][0]] if r["sweep_axis"] in AXES else np.nan for _, r in first.iterrows()]
    first = first.sort_values(["order", "value", "instance_key"], kind="stable")
    margins = sweep.pivot_table(index="instance_key", columns="model", values="margin_m", aggfunc="first",
                                dropna=False)
    models = list(dict.fromkeys(sweep["model"]))
    rows = pd.DataFrame({
        "instance": first["instance_key"], "condition": [_condition(r) for _, r in first.iterrows()],
        "slow vehicle": [_vehicle(p, b) for p, b in zip(first["sc_slow_paint"], first["sc_slow_body"])],
        "closing speed": [f"{num(v * 3.6)} km/h" for v in first["closing_speed_mps"]],
        "ideal": [num(v, 1) for v in first["ideal_margin_m"]],
        **{_label(m): [_margin(margins.loc[k, m]) if k in margins.index and m in margins.columns else "-"
                       for k in first["instance_key"]] for m in models}})
    return {"table": _table(rows, set(rows.columns) - {"instance", "condition", "slow vehicle"})}


def preset_margins(t: SampleTables) -> dict:
    """The SOTIF set's verdict: passes per model, the ideal margin per drive and the models' margins."""
    inst = t("sotif_instances", ["model", "set", "instance", "pass", "feasible", "margin_m", "ideal_margin_m"])
    sotif = inst[inst["set"] == "sotif"]
    passed = _passed(t).xs("sotif", level="set")
    drawn, drives = _drawn(t), []
    for i, g in sotif.groupby("instance"):
        name = "the study's drive" if i == 0 else ("the drawn one" if len(drawn) == 1 else f"drawn drive {i}")
        drives.append({"name": name if i == 0 or i > len(drawn) else f"{name} ({drawn[i - 1]})",
                       "ideal": span(g["ideal_margin_m"].min(), g["ideal_margin_m"].max(), 1),
                       "kept": span(g["margin_m"].min(), g["margin_m"].max(), 1) if g["margin_m"].notna().any()
                       else "nothing"})
    return {"presets": sotif_counts(t)["presets"], "n": _same(passed["n"].unique()),
            "all_pass": bool((passed["n_pass"] == passed["n"]).all()),
            "passes": span(passed["n_pass"].min(), passed["n_pass"].max()), "drives": drives}


def how_to_read(t: SampleTables) -> dict:
    """The sets behind the tables' numbers and what each interval resamples."""
    ov = t("overview", ["val frames"])
    rob = t("robustness", ["n_corrupt_presets"])
    pairs = t("pairs", ["metric", "unit", "n_units"])
    units = pairs.drop_duplicates("metric").set_index("metric")
    sotif = _instances(t, "sotif")
    t("sotif_instances", ["precipitation_class"])
    by_class = sotif.groupby("precipitation_class").size()
    sweep = _instances(t, "sweep")
    unit = lambda m: (f"{num(units.loc[m, 'n_units'])} {units.loc[m, 'unit']}s" if m in units.index else "?")
    return {"sotif": sotif_counts(t), "val_frames": _same(ov["val frames"].unique()),
            "corrupt": _same(rob["n_corrupt_presets"].unique()),
            "class_instances": " / ".join(num(by_class.get(c, 0)) for c in CLASSES),
            "drives": sotif["instance"].nunique(),
            "pairs_val": unit("val_ap3d_moderate"), "pairs_headline": unit("headline_ap3d"),
            "sweep_feasible": int(_true(sweep["feasible"]).sum()), "sweep_instances": len(sweep)}
