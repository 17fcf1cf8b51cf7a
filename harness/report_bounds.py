"""The report's boundaries: ``tables/sotif_boundaries.csv`` (written by ``harness.run_boundaries``) read back and
put in words, nothing recomputed.

Per reference scenario and axis a row of the lead table, each model's cell its boundary in words (``cell``), and
the whole file as a table of the "SOTIF over the scenario space" section with a caption saying what lo-hi are
under the run's plan (``caption``). A run made before the boundary searches has no file: no rows.
"""
from __future__ import annotations

from pathlib import Path

import pandas as pd

from harness.boundaries import BENIGN, LOG_AXES, STATUS_FAIL, STATUS_PASS, STATUS_WIDE, STATUS_WITHIN, TOLERANCE
from harness.core.kitti import KittiError
from harness.run_boundaries import COLUMNS, PLANS, TABLE

SET = "bounds"  # the lead table's set label of the boundary rows (the run's data/bounds probes)
AXES = {  # axis: (label in the lead table, decimals, unit after a number)
    "rain": ("rain (mm/h)", 0, " mm/h"), "fog": ("fog visibility (m)", 0, " m"),
    "water": ("road water (share of the road)", 2, ""), "reflectance": ("slow car reflectance at 905 nm", 2, ""),
}
NAMES = {"rain": "rain", "fog": "fog visibility", "water": "road water", "reflectance": "reflectance"}  # in prose
WORSE = {"lo": "above", "hi": "below"}  # benign end -> the side of the bracket on which a model fails
TEXT, NUMBERS = ("model", "axis", "scenario", "unit", "status"), ("lo", "hi", "n_probes")


def read(run_dir) -> pd.DataFrame:
    """The run's boundaries table (``COLUMNS``); empty when the run has none or the file is empty, a KittiError
    naming the file (and line) when it is not a CSV table with those columns, numbers in lo, hi and n_probes
    and no empty text."""
    path = Path(run_dir) / TABLE
    if not path.is_file():
        return pd.DataFrame(columns=list(COLUMNS))
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False)
    except pd.errors.EmptyDataError:
        return pd.DataFrame(columns=list(COLUMNS))
    except (pd.errors.ParserError, ValueError) as e:  # UnicodeDecodeError is a ValueError
        raise KittiError(path, f"not a readable CSV table ({e})") from None
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise KittiError(path, f"no {', '.join(missing)} column{'s' if len(missing) > 1 else ''}")
    for c in NUMBERS:
        values = pd.to_numeric(df[c], errors="coerce")
        bad = values.isna().to_numpy().nonzero()[0]
        if len(bad):
            raise KittiError(path, f"{c} is not a number ({df[c].iloc[bad[0]]!r})", line=int(bad[0]) + 2)
        df[c] = values.astype(int if c == "n_probes" else float)
    for c in TEXT:
        bad = (df[c].str.strip() == "").to_numpy().nonzero()[0]
        if len(bad):
            raise KittiError(path, f"empty {c}", line=int(bad[0]) + 2)
    return df[list(COLUMNS)].reset_index(drop=True)


def number(axis: str, value: float) -> str:
    """A probed value with the axis's digits: mm/h and m whole (thousands separated), shares two decimals."""
    digits = AXES[axis][1] if axis in AXES else None
    return f"{value:g}" if digits is None else f"{value:,.{digits}f}"


def span(axis: str, lo: float, hi: float, unit: str) -> str:
    """"25-50 mm/h": lo-hi with the axis's digits and its unit (none for a share or a reflectance)."""
    after = AXES[axis][2] if axis in AXES else f" {unit}"
    return f"{number(axis, lo)}-{number(axis, hi)}{after}"


def tolerance(axis: str) -> str:
    """The search's tolerance of an axis: "±5 mm/h", "±10 %" (fog, relative), "±0.05"; "the tolerance" when
    this report does not know the axis."""
    if axis not in TOLERANCE or axis not in AXES:
        return "the tolerance"
    tol = TOLERANCE[axis]
    return f"±{100 * tol:g} %" if axis in LOG_AXES else f"±{tol:g}{AXES[axis][2]}"


def cell(axis: str, lo: float, hi: float, unit: str, status: str) -> str:
    """A model's boundary on one axis in words: "fails above 25-50 mm/h" (the verdict flips inside the bracket,
    failing on the side away from the axis's benign end: above on rain and road water, below on fog visibility
    and reflectance), "(bracket wider than ±5 mm/h)" when it is not within the tolerance, "passes everywhere in
    0-100 mm/h", "fails everywhere in 0-100 mm/h"; any other status as it is; the status's notes after a ";"."""
    head, *notes = [s.strip() for s in str(status).split(";")]
    bracket = span(axis, lo, hi, unit)
    if head in (STATUS_WITHIN, STATUS_WIDE):
        side = WORSE.get(BENIGN.get(axis))
        words = f"fails {side} {bracket}" if side else f"flips between {bracket}"
        if head == STATUS_WIDE:
            words += f" (bracket wider than {tolerance(axis)})"
    elif head == STATUS_PASS:
        words = f"passes everywhere in {bracket}"
    elif head == STATUS_FAIL:
        words = f"fails everywhere in {bracket}"
    else:  # no verdict, unpreventable (reason), a status this report does not know
        words = head
    return "; ".join([words, *notes])


def condition(axis: str, scenario: str, unit: str) -> str:
    """"boundary: rain (mm/h), 120-60 sedan silver" (ego-slow car km/h, body, paint)."""
    label = AXES[axis][0] if axis in AXES else f"{axis} ({unit})"
    return f"boundary: {label}, {scenario.replace('_', ' ')}"


def lead_rows(bounds: pd.DataFrame) -> pd.DataFrame:
    """One row per (scenario, axis) in the file's order: set ``SET``, its condition, a column per model."""
    if bounds.empty:
        return pd.DataFrame()
    df = bounds.assign(condition=[condition(a, s, u) for a, s, u in zip(bounds["axis"], bounds["scenario"],
                                                                        bounds["unit"])],
                       cell=[cell(r.axis, r.lo, r.hi, r.unit, r.status) for r in bounds.itertuples()])
    wide = df.pivot_table(index="condition", columns="model", values="cell", aggfunc="first")
    wide = wide.reindex(index=list(dict.fromkeys(df["condition"])), columns=list(dict.fromkeys(df["model"])))
    return wide.rename_axis(columns=None).reset_index().assign(set=SET)[["set", "condition", *wide.columns]]


def with_rows(rows: pd.DataFrame, matrix: pd.DataFrame) -> pd.DataFrame:
    """The lead table: the boundary rows first, then ``report_space.rate_matrix``'s; models in the matrix's order,
    any only in the boundaries after them, the unpreventable column last ("–" on the boundary rows)."""
    if rows.empty or matrix.empty:
        return matrix if rows.empty else rows
    models = [c for c in matrix.columns if c not in ("set", "condition", "unpreventable")]
    models += [m for m in rows.columns[2:] if m not in models]
    last = ["unpreventable"] if "unpreventable" in matrix.columns else []
    out = pd.concat([rows, matrix], ignore_index=True)[["set", "condition", *models, *last]]
    return out.fillna({c: "–" for c in last})


def table(bounds: pd.DataFrame) -> pd.DataFrame:
    """The file as the report shows it: lo and hi with the axis's digits."""
    if bounds.empty:
        return pd.DataFrame()
    return bounds.assign(**{c: [number(a, v) for a, v in zip(bounds["axis"], bounds[c])] for c in ("lo", "hi")})


def _plan(summary: dict) -> str:
    """What the run's plan (``harness.run_boundaries.PLANS``) probed, in words."""
    name = (summary.get("config") or {}).get("bounds")
    plan = PLANS.get(name)
    if plan is None:
        return "plan not recorded" if name is None else f'plan "{name}", not one this version knows'
    grid = "its two ends" if plan.grid == 2 else f"{plan.grid} values, ends included"
    rounds = ("until all are within it" if plan.max_rounds is None else
              f"for at most {plan.max_rounds} round{'s' if plan.max_rounds != 1 else ''}")
    refine = ("no refinement" if plan.max_rounds == 0 else
              f"then the midpoint of each bracket wider than the tolerance {rounds}")
    seeds = (f"noise seed {plan.seeds[0]}" if len(plan.seeds) == 1 else
             f"noise seed {plan.seeds[0]}, the final brackets again with seeds "
             f"{', '.join(map(str, plan.seeds[1:]))}")
    return f'plan "{name}": per reference scenario and axis {grid}, {refine}, {seeds}'


def caption(summary: dict) -> str:
    """The boundaries table's caption: the plan, what lo-hi are, the tolerances."""
    tols = ", ".join(f"{tolerance(a)} {NAMES[a]}" for a in TOLERANCE if a in NAMES)
    return (f"Boundaries ({_plan(summary)}): for a bracketed model lo-hi are the neighbouring probed values nearest "
            "the benign end (no rain, clear air, a dry road, the brightest paint) across which its "
            "perception verdict flips, as narrow as the plan's probes resolved it (\"bracketed\" within the "
            f"tolerance, {tols}, else \"wider than the tolerance\"), and for every other status the whole axis "
            "searched; n probes: the (value, noise seed) probes of the search, shared by all models.")
