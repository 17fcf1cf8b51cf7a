"""The SOTIF verdict of a detector's predictions on a scenario set: ``sotif-bench verdict``, and ``run``.

Per scenario instance (its frames from the lane change on, ``harness.reference``):

- the *reference* confirms the slow vehicle by the confirmation rule (``harness.decision``) over the frames in
  which it is perceivable (>= 30 % of its footprint unoccluded and in range); the instance is *preventable*
  when that confirmation, plus the reaction time, leaves a_req <= 6 m/s^2. An unpreventable instance carries
  its reason (kinematics, occlusion, range) and never counts against a detector;
- a detector confirms it by the same rule over its in-path hits (``harness.inpath``): the *perception* verdict
  on every frame with no latency (the headline), the *system* verdict on the frames it can process at its
  latency (the measured p90), the latency added to the decision time;
- ``delay_s`` is the detector's decision (confirmation + latency) behind the reference's confirmation (0 when
  it is not behind), ``a_req_mps2`` the deceleration its decision leaves, ``margin_m`` the metres to spare at
  6 m/s^2, ``passed`` a_req <= 6 m/s^2 (``passed_4mps2``: <= 4 m/s^2). Never confirmed: a_req inf, failed.

Pass rates count preventable instances, car-bodied ones (the class the detectors learned) apart from vans and
trucks, with a Wilson 95 % interval over instances. Phantom braking: in-path boxes on no object per hour of
driving (judged frames x frame period) per weather, and confirmed phantom events (rising edges of the rule).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from harness import decision, reference
from harness.inpath import LIDAR_TO_FRONT_M
from harness.core.files import atomic_write_text
from harness.sotif_space import rate_row
from harness.core.visibility import VISIBLE_MIN
from harness.core.braking import A_PASS_MPS2, DECEL_MPS2, T_REACT_S, T_REACT_SYSTEM_S

VERDICTS = ("perception", "system")
REACTIONS = {"system": T_REACT_SYSTEM_S, "human": T_REACT_S}  # s, an automated system's (UN R157) / a driver's
INSTANCE_COLUMNS = ("instance", "body", "paint", "reflectance", "rain_mm_h", "fog_mor_m", "water", "preventable",
                    "reason", "reference_confirm_s", "model", "confirm_s", "delay_s", "a_req_mps2", "margin_m",
                    "passed", "verdict")
EXTRA_COLUMNS = ("weather", "sweep_axis", "precipitation_class", "body_class", "latency_ms", "reference_a_req_mps2",
                 "passed_4mps2", "box_iou05_share", "n_frames")
_CONDITIONS = {"paint": "sc_slow_paint", "reflectance": "sc_slow_reflectance", "rain_mm_h": "rain_rate_mmh",
               "fog_mor_m": "fog_mor_m", "water": "road_water", "sweep_axis": "sweep_axis",
               "precipitation_class": "precipitation_class"}
FRAME_COLUMNS = ("rain_rate_mmh", "fog_mor_m", "sc_slow_reflectance", "precipitation_class")  # kept per frame


@dataclass(frozen=True)
class Rule:
    """The confirmation rule and the pass criterion (sources in docs/simulator.md)."""

    k: int = decision.CONFIRM_K
    window_s: float = decision.CONFIRM_WINDOW_S
    reaction_s: float = T_REACT_SYSTEM_S
    a_pass_mps2: float = A_PASS_MPS2
    a_firm_mps2: float = DECEL_MPS2
    visible_min: float = VISIBLE_MIN


def _confirm(t: np.ndarray, hits: np.ndarray, rule: Rule) -> float | None:
    """Seconds after the lane change at which ``hits`` confirm the slow vehicle (None: never)."""
    window = decision.confirm_window(rule.window_s, rule.k, decision.frame_period(t))
    i = decision.confirm_index(t, hits, rule.k, window)
    return None if i is None else float(t[i])


def _decide(confirm_s: float | None, latency_s: float, d0: float, dv: float, rule: Rule) -> dict:
    """The outcome of a confirmation (None: never confirmed) with latency and reaction added."""
    if confirm_s is None:
        return {"a_req_mps2": math.inf, "margin_m": float("nan"), "passed": False, "passed_4mps2": False}
    out = decision.outcome(d0, dv, confirm_s + latency_s + rule.reaction_s)
    return {"a_req_mps2": round(out["a_req_mps2"], 4), "margin_m": round(out["margin_m"], 3),
            "passed": decision.passes(out["a_req_mps2"], rule.a_pass_mps2),
            "passed_4mps2": decision.passes(out["a_req_mps2"], rule.a_firm_mps2)}


def _reference_row(g: pd.DataFrame, d0: float, dv: float, rule: Rule) -> dict:
    """The instance's columns that do not depend on the detector: the reference and the conditions."""
    t = g["t_s"].to_numpy(float)
    first = g.iloc[0]
    ref_s = _confirm(t, g["perceivable"].to_numpy(bool), rule)
    ref = _decide(ref_s, 0.0, d0, dv, rule)
    reason = None

    def ok(hits) -> bool:  # would a reference confirming on these frames pass?
        return _decide(_confirm(t, hits, rule), 0.0, d0, dv, rule)["passed"]

    if not ref["passed"]:
        reason = decision.unpreventable_reason(ok(np.ones(len(t), bool)),
                                               ok(g["in_range"].to_numpy() >= rule.visible_min),
                                               ok(g["unoccluded"].to_numpy() >= rule.visible_min))
    body = str(first["sc_slow_body"])
    row = {"instance": str(first["instance_key"]), "weather": str(first["weather"]), "body": body,
           "body_class": reference.body_class(body), "preventable": bool(ref["passed"]), "reason": reason,
           "reference_confirm_s": ref_s, "reference_a_req_mps2": ref["a_req_mps2"], "n_frames": int(len(g))}
    for name, column in _CONDITIONS.items():
        row[name] = first[column] if column in g and pd.notna(first[column]) else None
    return row


def _model_rows(base: dict, t, hits, iou_hits, d0: float, dv: float, rule: Rule, model: str,
                latency_s: float | None) -> list[dict]:
    """The perception row, and the system row when the latency is known, of one detector on one instance."""
    rows = []
    for kind, lat in (("perception", 0.0), ("system", latency_s)):
        if lat is None:
            continue
        keep = decision.processed_frames(t, lat)
        confirm_s = _confirm(t[keep], hits[keep], rule)
        ref_s = base["reference_confirm_s"]
        delay = None if confirm_s is None or ref_s is None else round(max(0.0, confirm_s + lat - ref_s), 3)
        share = round(float(iou_hits[keep & hits].mean()), 4) if (keep & hits).any() else None
        rows.append({**base, "model": model, "verdict": kind, "latency_ms": round(1000.0 * lat, 3), "confirm_s": confirm_s,
                     "delay_s": delay, **_decide(confirm_s, lat, d0, dv, rule), "box_iou05_share": share})
    return rows


def instance_verdicts(ref: reference.Reference, det: pd.DataFrame, rule: Rule, model: str,
                      latency_s: float | None = None) -> pd.DataFrame:
    """One row per instance and verdict kind (module docstring); columns INSTANCE_COLUMNS + EXTRA_COLUMNS."""
    frames = ref.frames.join(det)
    rows = []
    for _, g in frames.groupby("instance_key", sort=False):
        first = g.iloc[0]
        d0 = float(first["rear_m"]) - LIDAR_TO_FRONT_M  # m, the ego's front bumper to the rear face
        dv = float(first["ego_speed_mps"] - first["slow_car_speed_mps"])
        base = _reference_row(g, d0, dv, rule)
        rows += _model_rows(base, g["t_s"].to_numpy(float), g["hit"].to_numpy(bool), g["iou_hit"].to_numpy(bool),
                            d0, dv, rule, model, latency_s)
    return pd.DataFrame(rows, columns=[*INSTANCE_COLUMNS, *EXTRA_COLUMNS])


def _weather_label(frames: pd.DataFrame) -> pd.Series:
    """The phantom table's grouping: the preset, or "Sweep: <axis>" for a sweep set's instances."""
    w = frames["weather"].astype(str)
    if "sweep_axis" not in frames:
        return w
    return w.where(frames["sweep_axis"].astype(str).isin(("preset", "nan")), w + ": " + frames["sweep_axis"].astype(str))


def phantom_rates(ref: reference.Reference, det: pd.DataFrame, rule: Rule, model: str) -> pd.DataFrame:
    """Per weather: judged frames, hours they stand for, phantom in-path boxes and confirmed phantom events
    (the rule's rising edges, per instance), each per hour."""
    frames = ref.frames.join(det).assign(_weather=lambda f: _weather_label(f))
    rows = []
    for weather, g in frames.groupby("_weather", sort=False):
        seconds, events = 0.0, 0
        for _, inst in g.groupby("instance_key", sort=False):
            t = inst["t_s"].to_numpy(float)
            period = decision.frame_period(t)
            seconds += len(t) * (period if np.isfinite(period) else 0.1)
            events += phantom_events(t, inst["n_phantom"].to_numpy() > 0, rule)
        hours = seconds / 3600.0
        n_false = int(g["n_phantom"].sum())
        rows.append({"model": model, "weather": weather, "n_frames": int(len(g)), "hours": hours, "n_false": n_false,
                     "false_per_h": n_false / hours if hours else float("nan"), "n_events": events,
                     "events_per_h": events / hours if hours else float("nan")})
    return pd.DataFrame(rows)


def phantom_events(t, flagged, rule: Rule) -> int:
    """Times the rule's confirmation state turns on over frames flagged with a phantom box."""
    t, f = np.asarray(t, float), np.asarray(flagged, bool)
    if t.size == 0:
        return 0
    window = decision.confirm_window(rule.window_s, rule.k, decision.frame_period(t))
    csum = np.r_[0, np.cumsum(f)]
    on = (csum[1:] - csum[np.searchsorted(t, t - window + 1e-6, side="left")]) >= rule.k
    return int((on & ~np.r_[False, on[:-1]]).sum())


def pass_summary(rows: pd.DataFrame) -> pd.DataFrame:
    """Per model, verdict kind and body class: the preventable instances passed, with a Wilson 95 % interval
    over instances (``n_drives``: the distinct drives behind them; weather copies of a drive share it)."""
    out = []
    for (model, kind, cls), g in rows.groupby(["model", "verdict", "body_class"], sort=False):
        p = g[g["preventable"]]
        drives = p["instance"].str.split("#").str[-1].nunique() if len(p) else 0
        out.append({"model": model, "verdict": kind, "body_class": cls, **rate_row(p["passed"].astype(bool)),
                    "unit": "instances", "n_drives": int(drives), "n_unpreventable": int((~g["preventable"]).sum())})
    return pd.DataFrame(out)


def frame_table(ref: reference.Reference, det: pd.DataFrame) -> dict:
    """The judged frames as lists (the report's detection maps): instance, gap to the slow vehicle's rear face
    (``distance_m``), ``hit``, ``perceivable`` and the frame's conditions."""
    f = ref.frames
    table = {"instance": f["instance_key"].astype(str).tolist(),
             "distance_m": (f["rear_m"] - LIDAR_TO_FRONT_M).round(3).tolist(), "hit": det["hit"].tolist(),
             "perceivable": f["perceivable"].tolist()}
    return table | {c: f[c].tolist() for c in FRAME_COLUMNS if c in f}


def verdict(data_dir, predictions_dir, threshold: float, latency_ms: float | None = None, split: str = "test",
            rule: Rule = Rule(), model: str | None = None, ref: reference.Reference | None = None) -> dict:
    """The verdict of one predictions folder on a scenario set (module docstring): ``{rule, threshold, model,
    n_frames, n_frames_predicted, instances, phantoms, summary, frames}`` (tables as lists of records; ``frames``
    as ``frame_table``)."""
    if latency_ms is not None and not latency_ms >= 0:
        raise ValueError(f"latency {latency_ms} ms: must be a number >= 0")
    reference.check_predictions(data_dir, predictions_dir)
    ref = ref if ref is not None else reference_of(data_dir, split, rule)
    model = model or Path(predictions_dir).name
    det = reference.detector_frames(ref, predictions_dir, threshold)
    rows = instance_verdicts(ref, det, rule, model, None if latency_ms is None else latency_ms / 1000.0)
    return {"rule": asdict(rule), "threshold": float(threshold), "model": model, "split": split,
            "n_frames": int(len(det)), "n_frames_predicted": int(det["predicted"].sum()),
            "instances": _records(rows), "phantoms": _records(phantom_rates(ref, det, rule, model)),
            "summary": _records(pass_summary(rows)), "frames": frame_table(ref, det)}


def reference_of(data_dir, split: str = "test", rule: Rule = Rule()) -> reference.Reference:
    return reference.reference_frames(data_dir, split, rule.visible_min)


def _records(df: pd.DataFrame) -> list[dict]:
    """JSON-ready rows: numpy scalars as Python numbers, NaN as None (inf stays)."""
    out = []
    for rec in df.to_dict("records"):
        out.append({k: (None if isinstance(v, float) and math.isnan(v) else v.item() if isinstance(v, np.generic)
                        else v) for k, v in rec.items()})
    return out


def write_verdict(path, result: dict) -> Path:
    """``path`` ending in .csv: the instance table; anything else: the whole result as JSON. Atomic."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        table = pd.DataFrame(result["instances"], columns=[*INSTANCE_COLUMNS, *EXTRA_COLUMNS])
        return atomic_write_text(path, table.to_csv(index=False, lineterminator="\n"))
    return atomic_write_text(path, json.dumps(result, indent=1, default=str) + "\n")
