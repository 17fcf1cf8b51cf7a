"""The scenario-space part of a run: the weather sweep set's predictions and evaluation, and each
model's SOTIF verdict over instances and calibration summary (``harness.verdict``, ``harness.calibration``).

The sweep set (``data/sweep``, ``RunConfig.sweep_instances`` instances over rain rate, fog visibility
and road water) is predicted into ``predictions_sweep/<model>/`` and evaluated into
``results/<model>.sweep.json`` grouped by ``SWEEP_GROUPS``, as the SOTIF set is. The summary adds to
each model of ``results.json``:

- ``sotif_space.<sotif|sweep>``: ``harness.verdict.verdict`` (rule, instances, phantoms, summary, frames)
  at the model's operating threshold (F1-optimal on the val frames), the system verdict at its onnxruntime latency p90
  (measured by the run's probe on this machine);
- ``calibration.<0.7|0.5>.<all|precipitation class>``: ``harness.calibration.calibration_view``
  over the SOTIF set's test frames.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from harness.predict_eval import predict_evaluate
from harness.stages import Stages

SWEEP_GROUPS = ("sweep_axis", "rain_rate_mmh", "fog_mor_m", "road_water", "precipitation_class")
SETS = ("sotif", "sweep")


def predictions_of(run_dir: Path, data_set: str, name: str) -> Path:
    """Where a run keeps a model's test predictions of a data set."""
    return run_dir / ("predictions" if data_set == "sotif" else f"predictions_{data_set}") / name


def predict_eval_sweep(stages: Stages, cfg, run_dir: Path, name: str, sweep_hash: str, runtime: str,
                       threads: int | None = None) -> None:
    """Predict the sweep set's test frames with a model's ONNX file and evaluate them."""
    predict_evaluate(stages, cfg, run_dir, name, "sweep_", run_dir / "data" / "sweep", sweep_hash, "test",
                     predictions_of(run_dir, "sweep", name), run_dir / "results" / f"{name}.sweep.json", runtime,
                     threads, group_by=SWEEP_GROUPS)


def latency_ms(runtime: dict) -> float | None:
    """The model's onnxruntime latency p90 in ms (None when it was not measured: no system verdict)."""
    p90 = ((runtime or {}).get("onnxruntime") or {}).get("latency_ms_p90")
    return float(p90) if isinstance(p90, (int, float)) else None


@lru_cache(maxsize=4)
def _reference(data: Path, stamp: int):
    """The reference of a data set's test split, once per set (and per meta/frames.csv) in a run's process."""
    from harness.verdict import reference_of
    return reference_of(data)


def space_summary(run_dir: Path, name: str, threshold: float, runtime: dict) -> dict:
    """``{"sotif_space": {set: verdict}, "calibration": ...}`` of one model (module docstring)."""
    from harness.calibration import calibration_view
    from harness.verdict import verdict
    views = {}
    for data_set in SETS:
        data, pred = run_dir / "data" / data_set, predictions_of(run_dir, data_set, name)
        if (data / "ImageSets" / "test.txt").is_file() and pred.is_dir():
            ref = _reference(data.resolve(), (data / "meta" / "frames.csv").stat().st_mtime_ns)
            views[data_set] = verdict(data, pred, threshold, latency_ms=latency_ms(runtime), model=name, ref=ref)
    return {"sotif_space": views,
            "calibration": calibration_view(run_dir / "data" / "sotif", predictions_of(run_dir, "sotif", name))}
