"""Short statements the report prints beside the tables they qualify, computed from the run's files:
how lenient the SOTIF criterion is, which presets the LiDAR cannot tell apart, that no preset has
LiDAR fog, and which val set each number comes from. Each returns a sentence or "" when the run
lacks the data."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from harness.cells import span
from harness.rain import lidar_twins


def sotif_leniency(sotif: pd.DataFrame) -> str:
    """How much room the one scripted cut-out per preset leaves (``sotif``: ``tables.sotif_table``)."""
    need = {"distance_at_lane_change_m", "closing_speed_mps", "stopping_distance_m", "distance_m", "verdict"}
    judged = sotif[sotif["verdict"] != "n/a"] if need <= set(sotif.columns) else pd.DataFrame()
    judged = judged.dropna(subset=["distance_at_lane_change_m", "closing_speed_mps"]) if len(judged) else judged
    if judged.empty:
        return ""
    d0, dv, stop = (judged[c].astype(float) for c in ("distance_at_lane_change_m", "closing_speed_mps",
                                                        "stopping_distance_m"))
    slack = ((d0 - stop) / dv.where(dv > 0)).min()
    found = judged["distance_m"].dropna().astype(float)
    seen = f"; detections came {span(found.min(), found.max())} m ahead" if len(found) else ""
    n_pass = int((judged["verdict"] == "pass").sum())
    return (f"How lenient this is: one scripted cut-out per preset (the study's), not a rate over scenario instances "
            "(the scenario-space section has those). At the lane "
            f"change the slow car is {span(d0.min(), d0.max())} m ahead and the ego closes at {dv.mean():.1f} m/s; "
            f"it needs {stop.max():.0f} m to brake, so a first detection up to {slack:.1f} s after the lane change "
            f"still passes{seen}. {n_pass} of {len(judged)} cells pass: a pass says the car was found in time in this "
            "one instance, not that a margin is left in harder ones.")


def lidar_twins_note(meta: pd.DataFrame | None) -> str:
    """Which presets the LiDAR cannot tell apart (same rain rate and road water) and why."""
    groups = lidar_twins(meta)
    if not groups:
        return ""
    shared = [g for g in groups if len(g) > 1]
    listed = "; ".join(" = ".join(g) for g in shared)
    return (f"The LiDAR tells {len(groups)} conditions apart among these {sum(map(len, groups))} presets: it sees rain "
            "rate and road water; time of day and cloudiness reach it only as sunlight false returns (p = 2e-4 "
            "sin(sun altitude) (1 - 0.75 cloudiness) per ray, docs/simulator.md), a few points per scan. Presets "
            f"with the same LiDAR condition: {listed}. Differences among them are noise of the frames, not weather.")


def fog_note(meta: pd.DataFrame | None) -> str:
    """Whether any preset of the run has fog the LiDAR sees (the presets' fog_density is CARLA's camera haze)."""
    if meta is None or "weather" not in meta.columns:
        return ""
    foggy = []
    column = next((c for c in ("lidar_fog_mor_m", "fog_mor_m") if c in meta.columns), None)
    if column:
        mor = meta.drop_duplicates("weather").set_index("weather")[column].astype(float)
        foggy = [w for w, v in mor.items() if v > 0]
    if foggy:
        return f"Presets with LiDAR fog: {', '.join(foggy)}."
    return ("No preset of this run has LiDAR fog: CARLA's fog_density is a rendering device of the camera image "
            "(its night presets carry 60-100 to darken it), a clear atmosphere at 905 nm; fog is simulated only for "
            "a fog visibility set explicitly: the sweep set's fog axis (50-2000 m, docs/simulator.md), when the run "
            "has one, is where fog shows.")


def _count(path: Path) -> int | None:
    return len(path.read_text(encoding="utf-8").split()) if path.is_file() else None


def val_sets(run_dir: Path, summary: dict) -> dict:
    """The val sets by name: ``valset`` (the run's own val set, data/val: held-out training-generator frames that
    give the val AP and the operating thresholds), ``sotif`` (the SOTIF data set's val split, which sets the
    operating thresholds when there is no val set) and ``training`` (the training set's own val split, the
    checkpoint's per-epoch series); frame counts or None."""
    data = Path(run_dir) / "data"
    return {"sotif": (summary.get("data") or {}).get("n_val_frames", _count(data / "sotif" / "ImageSets" / "val.txt")),
            "training": _count(data / "train" / "ImageSets" / "val.txt"),
            "valset": _count(data / "val_frames.txt")}


def val_header(vals: dict) -> str:
    """The report header's val frame counts, each named by what it is used for."""
    n = lambda v: "?" if v is None or (isinstance(v, float) and np.isnan(v)) else str(v)
    if vals.get("valset"):
        return f"val set {n(vals['valset'])} (val AP and operating thresholds)"
    return f"SOTIF val {n(vals['sotif'])} (operating thresholds), training val {n(vals['training'])} (val AP)"


def val_note(vals: dict) -> str:
    """One sentence naming the val sets."""
    n = lambda v: "?" if v is None or (isinstance(v, float) and np.isnan(v)) else str(v)
    if vals.get("valset"):
        return (f"One val set: \"val AP\" is KITTI moderate AP40 3D on the run's {n(vals['valset'])} held-out frames of "
                "the training generator (data/val), and each model's operating threshold (F1-optimal at BEV IoU "
                "0.5; the SOTIF verdict's score cut) comes from the same frames; the checkpoint's per-epoch series used "
                f"{n(vals['training'])} frames of the training set's own val split. None of them overlaps the SOTIF or sweep test sets.")
    return (f"Two val sets: \"val AP\" is KITTI moderate AP40 3D on {n(vals['training'])} held-out dry frames of the "
            f"training generator (training val); each model's operating threshold (the SOTIF verdict's score cut) "
            f"comes from the {n(vals['sotif'])} val frames of the SOTIF data set (SOTIF val). Neither overlaps the SOTIF "
            "test split.")
