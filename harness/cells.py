"""How the tables' numbers are written: what a KITTI AP over n ground-truth cars can reach at most
(and how a cell says so), and floats rounded where they are written.

KITTI picks its score thresholds at recall positions among the matched detections
(``harness.eval_kitti.get_thresholds``): n cars give k = min(n, 41) positions, so even a perfect
detector scores AP40 = 100 (k - 1) / 40 (AP40 skips the position at recall 0) and AP11 =
100 ceil(k / 4) / 11. Over 5 cars AP40 is at most 10, over 2 cars 2.5, over 0 cars it is 0 and
means nothing. A cap "binds" when it is below 100: for both, n <= 40.

``cap`` computes the cap by running KITTI's own threshold rule on n matches; ``ap_text`` writes
an AP with its count and cap for the command line; ``mark_capped`` turns the AP cells of a table
whose count column says they are capped or empty into text for the reports (the CSVs keep the
numbers and their count columns, rounded by ``round_floats``); ``num`` and ``span`` write a number
and a range in prose ("1,554", "31.8-32.6", and "68" where both ends read the same).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pandas as pd

from harness.eval_kitti import N_SAMPLE_PTS, ap_r11, ap_r40, get_thresholds

_AP = {"R40": ap_r40, "R11": ap_r11}
DIFFS = ("easy", "moderate", "hard")
DISTANCE_BINS = ("0-30", "30-50", "50-80")
# AP column -> (count column, AP kind), for the tables of harness.tables
CAP_COLUMNS = {
    **{c: ("n_car", "R40") for c in ("ap3d", "ap_bev", "ap3d_0.5")},
    **{c: ("n_gt_kitti_mod", "R40") for c in ("kitti_mod_3d", "kitti_mod_bev")},
    **{f"ap3d_{b}m": (f"n_gt_{b}m", "R40") for b in DISTANCE_BINS},
    **{f"AP{kind[1:]} {d}": (f"cars {d}", kind) for kind in ("R11", "R40") for d in DIFFS},
}


@lru_cache(maxsize=None)
def cap(n: int, kind: str = "R40") -> float:
    """The highest AP (percent) KITTI's ``kind`` ("R40" or "R11") can give over ``n`` ground-truth cars."""
    if n <= 0:
        return 0.0
    k = len(get_thresholds(np.arange(n, 0, -1, dtype=np.float64), n))  # recall positions n perfect matches reach
    return _AP[kind](np.r_[np.ones(k), np.zeros(N_SAMPLE_PTS - k)])


def binds(n: int, kind: str = "R40") -> bool:
    """True when an AP over ``n`` cars cannot reach 100 (or, with no cars, means nothing)."""
    return cap(n, kind) < 100.0


def ap_text(value: float, n: int, what: str = "cars", kind: str = "R40", digits: int = 2) -> str:
    """"12.34 (57 cars)", "10.00 (5 cars, at most 10.00)" or "no easy cars" (``what`` = "easy cars")."""
    if n <= 0:
        return f"no {what}"
    if binds(n, kind):
        return f"{value:.{digits}f} ({n} {_plural(n, what)}, at most {cap(n, kind):.{digits}f})"
    return f"{value:.{digits}f} ({n} {_plural(n, what)})"


def _plural(n: int, what: str) -> str:
    return what[:-1] if n == 1 and what.endswith("s") else what


def _cell(value, n, kind: str, digits: int):
    """A table cell: "n/a (0 cars)", "2.5 (≤ 2.5)" when the cap binds, else the value as it was."""
    if n is None or isinstance(value, str) or (isinstance(n, float) and math.isnan(n)) or pd.isna(value):
        return value
    n = int(n)
    if n == 0:
        return "n/a (0 cars)"
    return f"{value:.{digits}f} (≤ {cap(n, kind):.{digits}f})" if binds(n, kind) else value


def mark_capped(df: pd.DataFrame, digits: int) -> pd.DataFrame:
    """``df`` with each AP cell of ``CAP_COLUMNS`` whose count column is in ``df`` shown as empty or
    capped text (``_cell``); other cells, and rows without a count, are left as they are."""
    out = df.copy()
    for column, (count, kind) in CAP_COLUMNS.items():
        if column in out.columns and count in out.columns:
            out[column] = [_cell(v, n, kind, digits) for v, n in zip(out[column], out[count])]
    return out


def round_floats(df: pd.DataFrame, decimals: int = 4) -> pd.DataFrame:
    """``df`` with every float rounded to ``decimals`` decimals, or to two significant digits when it is
    smaller (a 7.6e-06 agreement error stays 7.6e-06), as files are written: no 34.599999999999994."""
    out = df.copy()
    for c in out.columns:
        if pd.api.types.is_float_dtype(out[c]):
            out[c] = out[c].map(lambda v: _round(v, decimals))
    return out


def _round(v: float, decimals: int) -> float:
    if not math.isfinite(v) or v == 0:
        return v
    return round(v, max(decimals, 1 - math.floor(math.log10(abs(v)))))


def num(v, digits: int = 0) -> str:
    """``v`` with ``digits`` decimals and thousands separated ("1,554", "47.5"); "-0.0" written "0.0"."""
    text = f"{float(v):,.{digits}f}"
    return text[1:] if text.lstrip("-").strip("0.,") == "" and text.startswith("-") else text


def span(lo, hi, digits: int = 0) -> str:
    """"31.8-32.6", or one number when both ends read the same ("68", not "68-68")."""
    a, b = num(lo, digits), num(hi, digits)
    return a if a == b else f"{a}-{b}"
