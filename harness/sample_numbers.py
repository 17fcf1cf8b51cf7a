"""The numbers the documents quote from a sample, computed from its ``tables/*.csv`` with pandas and written as
text (``harness.sample_docs`` lays them out with jinja2). Each public function takes a ``SampleTables`` and
returns the keyword arguments of the template macro of the same name; a table or column it needs and does not
find raises ``MissingTable`` naming the file.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from harness import report_bounds
from harness.cells import num, span
from harness.core.kitti import KittiError
from harness.report import MODEL_LABELS

AXES = {"rain": ("rain_mm_h", "rain", "mm/h", 1), "fog": ("fog_mor_m", "fog", "m", 0),  # sweep_axis ->
        "water": ("water", "water", "", 2)}  # (instance column, word, unit, decimals)
AXIS_WORDS = report_bounds.NAMES  # an axis in prose
PAINT = {"nir_black": "NIR-black"}
BODY = {"suv": "SUV"}
RAIN_GRADES = ("soft rain", "mid rain", "hard rain")
CLASSES = ("dry", "wet", "rain")
CARS, APART = "car", "outside the learned classes"  # harness.reference.body_class
INSTANCE_COLUMNS = ["model", "set", "instance", "verdict", "body", "paint", "reflectance", "preventable", "reason",
                    "reference_confirm_s", "reference_a_req_mps2", "confirm_s", "delay_s", "a_req_mps2", "passed",
                    "body_class"]


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


def _one(texts) -> str:
    """One text when all read the same, else each, comma-separated."""
    return texts[0] if len(set(texts)) == 1 else ", ".join(texts)


def _and(words) -> str:
    """"A", "A and B", "A, B and C"."""
    words = list(words)
    return ", ".join(words[:-1]) + f" and {words[-1]}" if len(words) > 1 else "".join(words)


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
def _verdicts(t: SampleTables) -> pd.DataFrame:
    """The instance table (``harness.verdict``): one row per model, set, instance and verdict kind."""
    return t("sotif_instances", INSTANCE_COLUMNS)


def _instances(t: SampleTables, data_set: str) -> pd.DataFrame:
    """The first model's perception rows of ``data_set``: one per instance (the reference, the conditions and
    the preventability are the same for every model)."""
    inst = _verdicts(t)
    rows = inst[(inst["set"] == data_set) & (inst["verdict"] == "perception")]
    if rows.empty:
        raise MissingTable(t.folder / "sotif_instances.csv", f"no instance of the {data_set!r} set")
    return rows[rows["model"] == rows["model"].iloc[0]]


def sotif_counts(t: SampleTables) -> dict:
    """The SOTIF test set: presets, instances per preset, frames, cars."""
    by_weather = t("data_by_weather", ["weather", "n_test"])
    detail = t("weather_detail", ["model", "n_car"])
    sotif = _instances(t, "sotif")
    t("sotif_instances", ["weather"])
    tested = by_weather[by_weather["n_test"] > 0]
    per_preset = sotif.groupby("weather").size()
    return {"presets": len(tested), "per_preset": _same(per_preset.unique()), "instances": len(sotif),
            "frames": num(tested["n_test"].sum()),
            "cars": num(detail[detail["model"] == detail["model"].iloc[0]]["n_car"].sum())}


def _rates(t: SampleTables) -> pd.DataFrame:
    """Per model, set, verdict and body class: preventable instances passed, with the Wilson interval."""
    rates = t("sotif_pass_rates", ["model", "set", "verdict", "body_class", "column", "n", "n_pass", "lo", "hi"])
    return rates[rates["column"] == "all"].set_index(["model", "set", "verdict", "body_class"])


def _rate(rates: pd.DataFrame, key: tuple, interval: bool = False) -> str:
    """"12/15", or "12/15 (0.55-0.93)" with the interval; "–" when the key has no row, "0/0" with none to judge."""
    if key not in rates.index:
        return "–"
    r = rates.loc[key]
    text = f"{int(r['n_pass'])}/{int(r['n'])}"
    return f"{text} ({r['lo']:.2f}-{r['hi']:.2f})" if interval and r["n"] > 0 else text


def _phantoms(t: SampleTables) -> pd.Series:
    """Phantom in-path boxes per hour over every judged frame of both scenario sets, per model."""
    ph = t("sotif_phantoms", ["model", "hours", "n_false"])
    g = ph.groupby("model", sort=False)[["n_false", "hours"]].sum()
    return g["n_false"] / g["hours"].where(g["hours"] > 0)


def _rain_rates(t: SampleTables, presets) -> list[str]:
    by_weather = t("data_by_weather", ["weather", "rain_rate_mmh"]).set_index("weather")["rain_rate_mmh"]
    return [f"{by_weather[p]:g}" if p in by_weather.index else "?" for p in presets]


def _drive(rows: pd.DataFrame) -> pd.Series:
    """The drive number of each instance key ("ClearNoon#1" -> 1; a key without one is the study's drive, 0)."""
    return rows["instance"].astype(str).str.extract(r"#(\d+)$")[0].fillna("0").astype(int)


def _preventable(rows: pd.DataFrame) -> pd.Series:
    return _true(rows["preventable"])


def _reasons(rows: pd.DataFrame) -> str:
    """"2 range, 1 kinematics" of the unpreventable instances of ``rows`` ("none" without any)."""
    counts = rows.loc[~_preventable(rows), "reason"].fillna("?").value_counts()
    return ", ".join(f"{n} {reason}" for reason, n in counts.items()) or "none"


# ----------------------------------------------------------------------------- README
def readme_table(t: SampleTables) -> dict:
    """The README's results table and the counts behind it."""
    ov = t("overview", ["model", "val AP3D mod", "val frames", "AP3D"])
    rain = t("rain", ["model", "iou", "condition", "group", "n_frames", "n_car", "ap"])
    rt = t("runtime", ["model", "ort_p50_ms", "ort_p90_ms", "size_mb"]).set_index("model")
    rates, phantoms = _rates(t), _phantoms(t)
    r05 = rain[rain["iou"].astype(float) == 0.5]
    ap = r05.pivot_table(index="model", columns="condition", values="ap", aggfunc="first")
    cell = lambda m, conds: " / ".join(num(ap.loc[m, c], 1) if m in ap.index and c in ap.columns and
                                       pd.notna(ap.loc[m, c]) else "–" for c in conds)
    models = list(ov["model"])
    val, head, draws = [num(v, 1) for v in ov["val AP3D mod"]], [num(v, 1) for v in ov["AP3D"]], _draws(t)
    if draws is not None:  # over the draws: mean (min-max); the other columns are the first draw's
        d = draws.set_index("model")
        spread = lambda m, col, own: (f"{num(d.loc[m, col + ' mean'], 1)} ({num(d.loc[m, col + ' min'], 1)}-"
                                      f"{num(d.loc[m, col + ' max'], 1)})" if m in d.index else own)
        val = [spread(m, "val AP3D mod", v) for m, v in zip(models, val)]
        head = [spread(m, "AP3D", v) for m, v in zip(models, head)]
    rows = pd.DataFrame({
        "model": [_label(m) for m in models], "val": val,
        "AP @0.7": head, "AP @0.5 dry / wet / rain": [cell(m, CLASSES) for m in models],
        "soft / mid / hard rain": [cell(m, RAIN_GRADES) for m in models],
        "sweep cars: perception": [_rate(rates, (m, "sweep", "perception", CARS), True) for m in models],
        "system": [_rate(rates, (m, "sweep", "system", CARS)) for m in models],
        "vans, trucks": [_rate(rates, (m, "sweep", "perception", APART)) for m in models],
        "presets": [_rate(rates, (m, "sotif", "perception", CARS)) for m in models],
        "phantoms": [f"{num(phantoms[m])}/h" if m in phantoms.index and pd.notna(phantoms[m]) else "–" for m in models],
        "latency p50 / p90": [f"{num(rt.loc[m, 'ort_p50_ms'])} / {num(rt.loc[m, 'ort_p90_ms'])} ms" if m in rt.index
                              else "–" for m in models],
        "ONNX": [f"{num(rt.loc[m, 'size_mb'], 1)} MB" if m in rt.index else "–" for m in models]})
    first = r05[r05["model"] == r05["model"].iloc[0]].set_index("condition")
    sweep = _instances(t, "sweep")
    cars = sweep[sweep["body_class"] == CARS]
    return {"table": _table(rows, set(rows.columns) - {"model", "AP @0.5 dry / wet / rain", "soft / mid / hard rain"}),
            "sotif": sotif_counts(t), "val_frames": _same(ov["val frames"].unique()),
            "class_frames": " / ".join(num(first.loc[c, "n_frames"]) for c in CLASSES),
            "class_cars": " / ".join(num(first.loc[c, "n_car"]) for c in CLASSES),
            "grade_rates": " / ".join(_rain_rates(t, [first.loc[g, "group"] for g in RAIN_GRADES])),
            "grade_frames": _each([first.loc[g, "n_frames"] for g in RAIN_GRADES], "frames"),
            "sweep_instances": len(sweep), "sweep_axes": _axes_words(sweep), "sweep_cars": len(cars),
            "sweep_preventable": int(_preventable(cars).sum()), "sweep_apart": len(sweep) - len(cars),
            "draws": None if draws is None else _same(draws["draws"].unique()),
            "seeds": None if draws is None else _one([_seeds(v) for v in draws["seeds"].astype(str).unique()])}


def _seeds(text: str) -> str:
    """"0-2" for the seeds "0,1,2" of a draws row, "0, 3" for "0,3"."""
    seeds = [int(v) for v in text.split(",")]
    run = len(seeds) > 2 and seeds == list(range(seeds[0], seeds[0] + len(seeds)))
    return f"{seeds[0]}-{seeds[-1]}" if run else ", ".join(map(str, seeds))


def _draws(t: SampleTables) -> pd.DataFrame | None:
    """``tables/draws.csv`` of a sample of more than one training draw per model, else None."""
    if not (t.folder / "draws.csv").is_file():
        return None
    draws = t("draws", ["model", "draws", "seeds", "val AP3D mod mean", "val AP3D mod min", "val AP3D mod max",
                        "AP3D mean", "AP3D min", "AP3D max"])
    return draws if (draws["draws"] > 1).any() else None


def _axes_words(sweep: pd.DataFrame) -> str:
    axes = [AXIS_WORDS.get(a, a) for a in dict.fromkeys(sweep["sweep_axis"]) if isinstance(a, str)] \
        if "sweep_axis" in sweep.columns else []
    return _and(axes)


def boundaries(t: SampleTables) -> dict:
    """Each model's boundary per reference scenario and axis (``harness.report_bounds``'s words), and the plan's
    probe count."""
    bounds = t("sotif_boundaries", ["model", "axis", "scenario", "lo", "hi", "unit", "status", "n_probes"])
    if bounds.empty:
        raise MissingTable(t.folder / "sotif_boundaries.csv", "no boundary rows")
    rows = report_bounds.lead_rows(bounds).drop(columns="set").fillna("–")
    rows = rows.rename(columns={**{m: _label(m) for m in rows.columns}, "condition": "axis, reference scenario"})
    rows["axis, reference scenario"] = rows["axis, reference scenario"].str.removeprefix("boundary: ")
    first = bounds[bounds["model"] == bounds["model"].iloc[0]]
    return {"table": _table(rows, set()), "scenarios": len(first["scenario"].unique()),
            "axes": len(first["axis"].unique()), "probes": int(first["n_probes"].sum())}


PAIR_METRICS = {"val_ap3d_moderate": "val AP", "headline_ap3d": "the SOTIF headline AP @0.7"}
PAIR_UNITS = {"frame": "frames", "instance": "instances"}
PAIR_SETS = {"val_ap3d_moderate": "val", "headline_ap3d": "SOTIF"}  # the set each metric's units are drawn from
SET_WORDS = {"sotif": "SOTIF", "sweep": "sweep"}


def _above(rows: pd.DataFrame, models: list[str]) -> str:
    """The pairs of one metric that are apart, as "A above B and C (by 2.0-6.8 points)" per model that is above
    another (most pairs won first; "every other model" when it is above all), or "no pair is apart"."""
    wins: dict[str, list] = {}
    for r in rows[_true(rows["apart"])].itertuples(index=False):  # the interval's side names the better model
        win, lose = (r.model_a, r.model_b) if r.ci_lo > 0 else (r.model_b, r.model_a)
        wins.setdefault(win, []).append((lose, abs(float(r.mean_diff))))
    present = set(rows["model_a"]) | set(rows["model_b"])
    everyone = list(dict.fromkeys([*models, *sorted(present)]))
    phrases = []
    for m in sorted(wins, key=lambda m: (-len(wins[m]), everyone.index(m))):
        losers = sorted(wins[m], key=lambda x: everyone.index(x[0]))
        others = present - {m}
        whom = "every other model" if len(others) > 1 and {x for x, _ in losers} >= others \
            else _and(_label(x) for x, _ in losers)
        diffs = [d for _, d in losers]
        phrases.append(f"{_label(m)} above {whom} (by {span(min(diffs), max(diffs), 1)} points)")
    return "; ".join(phrases) if phrases else "no pair is apart"


def _passes_more(data_set: str, verdict: str, a: str, b: str, a_only: int, b_only: int) -> str:
    """"B passes more of the sweep instances than A (perception: 9 against 1 passed by one of the two only)"."""
    win, lose = (a, b) if a_only > b_only else (b, a)
    return (f"{_label(win)} passes more of the {SET_WORDS.get(data_set, data_set)} instances than {_label(lose)} "
            f"({verdict}: {max(a_only, b_only)} against {min(a_only, b_only)} passed by one of the two only)")


def _pair_draws(pairs: pd.DataFrame) -> list:
    """The training draws per model that ``tables/pairs.csv``'s comparisons resample, each count once."""
    return sorted(set(pairs["n_draws_a"]) | set(pairs["n_draws_b"]))


def rankings(t: SampleTables) -> dict:
    """Which pairs of models ``tables/pairs.csv`` separates (their 95 % interval over frames or instances and
    training draws excludes 0) on val AP and the SOTIF headline, and which pairs ``tables/sotif_pairs.csv``
    separates on the SOTIF verdict (McNemar p < 0.05)."""
    pairs = t("pairs", ["model_a", "model_b", "metric", "mean_diff", "ci_lo", "apart", "unit", "n_units",
                        "n_draws_a", "n_draws_b"])
    verdicts = t("sotif_pairs", ["set", "verdict", "model_a", "model_b", "a_only", "b_only", "apart"])
    models = list(t("overview", ["model"])["model"])
    metrics = [m for m in PAIR_METRICS if (pairs["metric"] == m).any()]
    if not metrics:
        raise MissingTable(t.folder / "pairs.csv", f"no rows of {' or '.join(PAIR_METRICS)}")
    draws = _pair_draws(pairs)
    units = [f"{num(n)} {PAIR_SETS[m]} {PAIR_UNITS.get(u, u)}" for m, u, n in
             pairs.drop_duplicates("metric").set_index("metric").loc[metrics, ["unit", "n_units"]].itertuples()]
    apart = verdicts[_true(verdicts["apart"])]
    verdict = "; ".join(_passes_more(*r) for r in apart[["set", "verdict", "model_a", "model_b", "a_only",
                                                         "b_only"]].itertuples(index=False)) or "no pair is apart"
    return {"metrics": [{"name": PAIR_METRICS[m], "above": _above(pairs[pairs["metric"] == m], models)}
                        for m in metrics],
            "units": _and(units), "draws": _same(draws, sep=" or "), "one_draw": draws == [1],
            "verdict": verdict}


# ----------------------------------------------------------------------------- docs/results.md
def _vehicle_row(row) -> str:
    """"NIR-black SUV, reflectance 0.60" of an instance row."""
    refl = f", reflectance {row['reflectance']:.2f}" if pd.notna(row["reflectance"]) else ""
    return f"{_vehicle(row['paint'], row['body'])}{refl}"


def _drawn(t: SampleTables) -> list[str]:
    """The SOTIF set's drawn drives (instance number > 0), each as its slow vehicle's words."""
    sotif = _instances(t, "sotif")
    return [_vehicle_row(g.iloc[0]) for n, g in sotif.groupby(_drive(sotif), sort=True) if n > 0]


def data_sets(t: SampleTables) -> dict:
    """The three data sets of the sample: SOTIF, sweep, val."""
    ov = t("overview", ["val frames"])
    sweep = _instances(t, "sweep")
    t("sotif_instances", ["sweep_axis", *(a[0] for a in AXES.values())])
    per_axis = sweep.groupby("sweep_axis", sort=False).size()
    axes = []
    for axis, rows in sweep.groupby("sweep_axis", sort=False):
        if axis not in AXES:
            axes.append(AXIS_WORDS.get(axis, axis))
            continue
        column, _, unit, digits = AXES[axis]
        axes.append(f"{AXIS_WORDS[axis]} {span(rows[column].min(), rows[column].max(), digits)} {unit}".rstrip())
    cars = sweep[sweep["body_class"] == CARS]
    return {"sotif": sotif_counts(t), "drawn": _drawn(t), "sweep_instances": len(sweep),
            "per_axis": f"{per_axis.iloc[0]} per weather axis" if per_axis.nunique() == 1 else
            ", ".join(f"{AXIS_WORDS.get(a, a)} {n}" for a, n in per_axis.items()), "axes": axes,
            "cars": len(cars), "cars_preventable": int(_preventable(cars).sum()), "cars_reasons": _reasons(cars),
            "apart": len(sweep) - len(cars), "val_frames": _same(ov["val frames"].unique())}


def _condition(row) -> str:
    if row["sweep_axis"] not in AXES:
        return str(row["sweep_axis"])
    column, word, unit, digits = AXES[row["sweep_axis"]]
    return f"{word} {num(row[column], digits)} {unit}".rstrip()


def _a_req(v, preventable: bool) -> str:
    """A model's a_req cell: m/s^2 to one decimal, "never" when it never confirmed, "–" on an unpreventable one."""
    if not preventable:
        return "–"
    return "never" if pd.isna(v) or not np.isfinite(float(v)) else num(v, 1)


def sweep_instances(t: SampleTables) -> dict:
    """One row per sweep instance: its condition, slow vehicle, whether it is preventable (else why not), the
    reference's confirmation and a_req, and each model's perception a_req."""
    inst = _verdicts(t)
    t("sotif_instances", ["sweep_axis", *(a[0] for a in AXES.values())])
    sweep = inst[(inst["set"] == "sweep") & (inst["verdict"] == "perception")]
    first = _instances(t, "sweep").copy()
    first["order"] = [list(AXES).index(a) if a in AXES else len(AXES) for a in first["sweep_axis"]]
    first["value"] = [r[AXES[r["sweep_axis"]][0]] if r["sweep_axis"] in AXES else np.nan for _, r in first.iterrows()]
    first["number"] = _drive(first)
    first = first.sort_values(["order", "value", "number"], kind="stable")
    a_req = sweep.pivot_table(index="instance", columns="model", values="a_req_mps2", aggfunc="first", dropna=False)
    models = list(dict.fromkeys(sweep["model"]))
    ok = dict(zip(first["instance"], _preventable(first)))
    rows = pd.DataFrame({
        "instance": first["instance"], "condition": [_condition(r) for _, r in first.iterrows()],
        "slow vehicle": [_vehicle_row(r) for _, r in first.iterrows()],
        "preventable": ["yes" if p else f"no: {r}" for p, r in zip(_preventable(first), first["reason"].fillna("?"))],
        "reference": [f"{num(s, 1)} s, {num(a, 1)}" if pd.notna(s) and np.isfinite(float(a)) else "never"
                      for s, a in zip(first["reference_confirm_s"], first["reference_a_req_mps2"])],
        **{_label(m): [_a_req(a_req.loc[k, m], ok[k]) if k in a_req.index and m in a_req.columns else "–"
                       for k in first["instance"]] for m in models}})
    return {"table": _table(rows, set(rows.columns) - {"instance", "condition", "slow vehicle", "preventable",
                                                       "reference"})}


def preset_verdict(t: SampleTables) -> dict:
    """The SOTIF set's verdict: preventable instances, passes per model and verdict, the reference's a_req per
    drive and the models' delays behind it."""
    inst = _verdicts(t)
    sotif = inst[inst["set"] == "sotif"]
    first = _instances(t, "sotif")
    rates = _rates(t)
    drawn, drives = _drawn(t), []
    for i, (n, g) in enumerate(first.groupby(_drive(first), sort=True)):
        name = "the study's drive" if i == 0 else (f"the drawn one ({drawn[i - 1]})" if i <= len(drawn) else f"drive {n}")
        a = g.loc[_preventable(g), "reference_a_req_mps2"]
        drives.append({"name": name, "reference": span(a.min(), a.max(), 1) if len(a) else "none"})
    models = list(dict.fromkeys(sotif["model"]))
    cells = {kind: [_rate(rates, (m, "sotif", kind, CARS)) for m in models] for kind in ("perception", "system")}
    perception = sotif[(sotif["verdict"] == "perception") & _preventable(sotif)]
    delay = perception["delay_s"].dropna()
    a_req = perception["a_req_mps2"].replace(np.inf, np.nan).dropna()
    return {"presets": sotif_counts(t)["presets"], "n": len(first), "preventable": int(_preventable(first).sum()),
            "reasons": _reasons(first), "same": {k: len(set(v)) == 1 for k, v in cells.items()},
            "perception": _one(cells["perception"]), "system": _one(cells["system"]),
            "models": ", ".join(_label(m) for m in models), "drives": drives,
            "a_req": span(a_req.min(), a_req.max(), 1) if len(a_req) else "none",
            "delay": span(delay.min(), delay.max(), 2) if len(delay) else "none"}


def how_to_read(t: SampleTables) -> dict:
    """The sets behind the tables' numbers and what each interval resamples."""
    ov = t("overview", ["val frames"])
    rob = t("robustness", ["n_corrupt_presets"])
    pairs = t("pairs", ["metric", "unit", "n_units", "n_draws_a", "n_draws_b"])
    units = pairs.drop_duplicates("metric").set_index("metric")
    draws = _pair_draws(pairs)
    sotif = _instances(t, "sotif")
    t("sotif_instances", ["precipitation_class"])
    by_class = sotif.groupby("precipitation_class").size()
    sweep = _instances(t, "sweep")
    cars = sweep[sweep["body_class"] == CARS]
    unit = lambda m: (f"{num(units.loc[m, 'n_units'])} {PAIR_UNITS.get(units.loc[m, 'unit'], units.loc[m, 'unit'])}"
                      if m in units.index else "?")
    drives = _drive(sotif).nunique()
    return {"sotif": sotif_counts(t), "val_frames": _same(ov["val frames"].unique()),
            "corrupt": _same(rob["n_corrupt_presets"].unique()),
            "class_instances": " / ".join(num(by_class.get(c, 0)) for c in CLASSES), "drives": drives,
            "pairs_val": unit("val_ap3d_moderate"), "pairs_headline": unit("headline_ap3d"),
            "sweep_preventable": int(_preventable(cars).sum()), "sweep_cars": len(cars),
            "draws": None if draws == [1] else _same(draws, sep=" or ")}
