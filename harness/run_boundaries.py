"""The boundary part of a run: controlled sweeps that place each detector's boundary (``harness.boundaries``).

A plan (``PLANS``, named by ``RunConfig.bounds``) lists reference scenarios and axes (``simulator.bounds``);
one search per (scenario, axis) covers every model. The searches' next probes go out together, one round at a
time, each round three kinds of stage:

- ``simulate_bounds_r<r>``: the round's probes not judged in an earlier round into ``data/bounds/r<r>/``
  (``simulate --preset bounds``; every frame test), keyed by the probes, the seed and the generator version;
- ``predict_bounds_r<r>_<model>``: the model's ONNX file on them into ``predictions_bounds/r<r>/<model>/``,
  keyed by the file, the data set and the runtime;
- ``verdict_bounds_r<r>``: per model and probe the perception verdict (``harness.verdict``: every frame, no
  latency, the model's operating threshold): a_req, passed, and whether the reference could pass.

A probe whose instance is unpreventable (the reference, weather-blind, cannot pass: the same for every probe of a
reference scenario) has no verdict; such a search says so. Rain 0 and road water 0 are the reference scenario
itself and are simulated once per seed. Resumed runs replay the rounds from the stages' records, so only a
round whose probes or models changed runs again. Writes ``tables/sotif_boundaries.csv`` (``COLUMNS``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import pandas as pd

from harness.boundaries import SEEDS, STATUS_NONE, Search, axis, drive
from harness.core.files import atomic_write_text
from harness.stages import Stages, file_digest
from simulator.bounds import AXES, STUDY_REFERENCE, Probe

COLUMNS = ("model", "axis", "scenario", "lo", "hi", "unit", "status", "n_probes")
DATA_PARTS = ("training/velodyne", "training/image_2", "training/calib", "training/label_2", "training/planes",
              "ImageSets", "meta")
SEED_OFFSET = 3000  # the bounds sets' simulation seed: the run's seed + this
TABLE = Path("tables") / "sotif_boundaries.csv"


@dataclass(frozen=True)
class BoundsPlan:
    """Which searches a run makes and how far: ``grid`` values first, at most ``max_rounds`` refinements (None:
    until every bracket is within its tolerance), the final brackets rerun with ``seeds``."""

    scenarios: tuple[str, ...]
    axes: tuple[str, ...] = AXES
    grid: int = 3
    max_rounds: int | None = None
    seeds: tuple[int, ...] = SEEDS


PLANS = {
    # a smoke test of the stages: one short scenario, one axis, its two ends, one seed
    "quick": BoundsPlan(("120-60_sedan_silver",), ("reflectance",), grid=2, max_rounds=0, seeds=(0,)),
    # two reference scenarios of the short-window kinematics (36 frames a probe), four axes: the ends, then
    # midpoints until every bracket is within its tolerance, the final brackets rerun with three noise seeds
    # (docs/performance.md: about a quarter of an hour of the two cores)
    "default": BoundsPlan(("120-60_sedan_silver", "120-60_suv_black"), grid=2),
    # the boundaries to the tolerances with three seeds at the final brackets: several times the budget
    "tolerance": BoundsPlan((STUDY_REFERENCE, "120-60_suv_black")),
}


def canonical(p: Probe) -> Probe:
    """Rain 0 and road water 0 are the reference scenario itself: one probe for both."""
    return Probe(p.scenario, "rain", 0.0, p.noise_seed) if p.axis in ("rain", "water") and p.value == 0 else p


def _round(stages: Stages, cfg, run_dir: Path, r: int, probes: list[Probe], models: dict[str, float],
           runtime: str, threads: int | None) -> dict[Probe, dict]:
    """Simulate, predict and judge one round's probes: ``{probe: {model: a_req or None}}`` (None: unpreventable)."""
    from harness.infer import predict
    from harness.verdict import reference_of, verdict
    from simulator import generate
    from simulator.dataset import GENERATOR_VERSION
    data = run_dir / "data" / "bounds" / f"r{r}"
    seed = cfg.seed + SEED_OFFSET
    key = {"probes": [asdict(p) for p in probes], "seed": seed, "lidar": cfg.lidar_model,
           "generator": GENERATOR_VERSION}
    stages.run(f"simulate_bounds_r{r}", key, lambda: {"out": str(generate(
        data, preset="bounds", probes=probes, seed=seed, workers=cfg.workers, lidar_model=cfg.lidar_model,
        progress=stages.progress, force=True))}, outputs=[data / part for part in DATA_PARTS], by_stat=True)
    data_hash = file_digest(data / "meta" / "dataset.json")
    preds = {}
    for name in models:
        onnx, preds[name] = run_dir / "models" / f"{name}.onnx", run_dir / "predictions_bounds" / f"r{r}" / name
        stages.run(f"predict_bounds_r{r}_{name}", {"onnx": file_digest(onnx), "data": data_hash, "runtime": runtime},
                   lambda: {"summary": predict(onnx, data, preds[name], split="test", runtime=runtime, progress=False,
                                               threads=threads)}, outputs=[preds[name]])

    def judge() -> dict:
        ref = reference_of(data)
        out = {}
        for name, threshold in models.items():
            rows = verdict(data, preds[name], threshold, model=name, ref=ref)["instances"]
            out[name] = {row["instance"]: {"a_req": row["a_req_mps2"], "preventable": row["preventable"],
                                           "reason": row["reason"]} for row in rows if row["verdict"] == "perception"}
        return {"verdicts": out}
    info = stages.run(f"verdict_bounds_r{r}", {"data": data_hash, "thresholds": models,
                                               "predictions": {n: stages.outputs_digest(f"predict_bounds_r{r}_{n}")
                                                               for n in models}}, judge)
    return {p: {n: info["verdicts"][n][f"Sweep#{i}"] for n in models} for i, p in enumerate(probes)}


def search_boundaries(stages: Stages, cfg, run_dir: Path, models: dict[str, float], runtime: str,
                      threads: int | None = None, plan: BoundsPlan | None = None) -> Path:
    """Run the plan's searches for ``models`` ({name: operating threshold}); writes and returns the table."""
    plan = plan or PLANS[cfg.bounds]
    cells = [(s, a) for s in plan.scenarios for a in plan.axes]
    searches = [Search(axis(a), models, plan.grid, plan.max_rounds, plan.seeds) for _, a in cells]
    judged: dict[Probe, dict] = {}  # {probe: {model: verdict}} of every round so far
    reasons: dict[str, str] = {}  # scenario: why the reference cannot pass
    rounds = [0]

    def batch(asks):
        wanted = {(i, v, s): canonical(Probe(cells[i][0], cells[i][1], v, s)) for i, v, s in asks}
        new = sorted({p for p in wanted.values() if p not in judged}, key=lambda p: tuple(asdict(p).values()))
        if new:
            judged.update(_round(stages, cfg, run_dir, rounds[0], new, models, runtime, threads))
            rounds[0] += 1
        out = {}
        for ask, p in wanted.items():
            out[ask] = {name: v["a_req"] if v["preventable"] else None for name, v in judged[p].items()}
            reasons.update({p.scenario: v["reason"] for v in judged[p].values() if not v["preventable"]})
        return out
    drive(searches, batch)
    rows = []
    for (scenario, name), srch in zip(cells, searches):
        for model in models:
            row = srch.row(model)
            if row["status"] == STATUS_NONE and scenario in reasons:
                row["status"] = f"unpreventable ({reasons[scenario]})"
            rows.append({"model": model, "axis": name, "scenario": scenario, **row, "unit": srch.axis.unit})
    path = run_dir / TABLE
    atomic_write_text(path, pd.DataFrame(rows, columns=list(COLUMNS)).to_csv(index=False, lineterminator="\n"))
    return path


def boundaries_stage(stages: Stages, cfg, run_dir: Path, summary: dict, runtime: str) -> None:
    """``run``'s hook: the searches of ``cfg.bounds`` (none when None) for the models of ``summary`` at their
    operating thresholds (F1-optimal on the val frames)."""
    if cfg.bounds is None:
        return
    thresholds = {name: float(next(iter(entry["sotif"].values()))["threshold"]) for name, entry in summary.items()}
    search_boundaries(stages, cfg, run_dir, thresholds, runtime)
