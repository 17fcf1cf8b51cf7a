"""A run's val set: ``RunConfig.val_frames`` held-out training-generator frames, every one of them val.

The training set's own val split (270 frames of the default run's 1,800; the checkpoint's ``val_ap`` and the
per-epoch ``val_history``) is too small to rank models: a reseed moves it by several points. This set is
simulated apart from the training set (``--preset train`` with the seed ``seed + VAL_SEED_OFFSET``, in
``data/val``; the training set and its stage key stay as they are), every model's every training draw
predicts all of its frames (``predictions_valset/<tag>/``) and is evaluated with the KITTI protocol
(``results_valset/<tag>.json``). Its AP40 3D moderate @0.7 is the ``val`` of ``results.json``'s models and
draws (``val.3d_moderate``, ``val.n_frames``).
"""
from __future__ import annotations

import json
from pathlib import Path

from harness import predict_eval
from harness.core.files import atomic_write_text
from harness.core.kitti import read_frames_meta
from harness.stages import Stages, file_digest

VAL_SEED_OFFSET = 2000  # the training set is simulated with seed + 1000, the SOTIF set with seed
VAL_DATA = Path("data") / "val"
FRAME_LIST = Path("data") / "val_frames.txt"  # every frame id of data/val, one a line (an ImageSets file)
RESULTS = "results_valset"
VALSET_PREDICTIONS = "predictions_valset"  # one folder per draw tag: predictions of every frame of data/val


def simulate(stages: Stages, cfg, run_dir: Path, parts: tuple[str, ...]) -> str | None:
    """Simulate (or resume) the val set and list its frames; returns its ``meta/dataset.json``'s hash
    (None when ``cfg.val_frames`` is None: no val set)."""
    if not cfg.val_frames:
        return None
    from simulator import generate
    from simulator.dataset import GENERATOR_VERSION
    out, seed = run_dir / VAL_DATA, cfg.seed + VAL_SEED_OFFSET
    key = {"preset": "train", "frames": cfg.val_frames, "seed": seed, "lidar": cfg.lidar_model,
           "generator": GENERATOR_VERSION, "all_val": True}

    def make() -> dict:
        generate(out, preset="train", frames=cfg.val_frames, seed=seed, workers=cfg.workers,
                 lidar_model=cfg.lidar_model, progress=stages.progress, force=True)
        ids = read_frames_meta(out / "meta" / "frames.csv")["frame_id"].tolist()
        atomic_write_text(run_dir / FRAME_LIST, "".join(f"{i}\n" for i in ids))
        return {"out": str(out), "frames": len(ids)}
    stages.run("simulate_val", key, make, outputs=[out / p for p in parts] + [run_dir / FRAME_LIST], by_stat=True)
    return file_digest(out / "meta" / "dataset.json")


def predict_evaluate(stages: Stages, cfg, run_dir: Path, tag: str, runtime: str, threads: int | None) -> None:
    """Predict every frame of the val set with a draw's ONNX file and evaluate it (nothing without a val set)."""
    if not cfg.val_frames or not (run_dir / FRAME_LIST).is_file():
        return
    data = run_dir / VAL_DATA
    predict_eval.predict_evaluate(stages, cfg, run_dir, tag, "valset_", data,
                                  file_digest(data / "meta" / "dataset.json"), run_dir / FRAME_LIST,
                                  run_dir / VALSET_PREDICTIONS / tag, run_dir / RESULTS / f"{tag}.json", runtime,
                                  threads, bars=False, keyed_bootstrap=False)


def val_summary(run_dir: Path, tag: str) -> dict | None:
    """``{"3d_moderate", "bev_moderate", "n_frames", "n_car", "results"}`` of a draw on the val set (AP in %),
    None without one."""
    path = run_dir / RESULTS / f"{tag}.json"
    if not path.is_file():
        return None
    res = json.loads(path.read_text())
    r40 = lambda metric: res["kitti"][metric]["0.7"]["R40"]["moderate"]
    return {"3d_moderate": r40("3d"), "bev_moderate": r40("bev"), "n_frames": res["n_frames"], "n_car": res["n_car"],
            "data": f"val: {res['n_frames']} held-out training-generator frames",
            "results": f"{RESULTS}/{tag}.json"}


def threshold_of(run_dir: Path, tag: str) -> dict:
    """``{"threshold", "threshold_source"}`` for ``harness.sotif.sotif_view``: the F1-optimal score threshold
    of a draw on the whole val set; {} without one (the SOTIF set's own val split then picks it)."""
    from harness.sotif import operating_threshold
    pred = run_dir / VALSET_PREDICTIONS / tag
    if not (run_dir / FRAME_LIST).is_file() or not pred.is_dir():
        return {}
    thr, source = operating_threshold(run_dir / VAL_DATA, pred, split=run_dir / FRAME_LIST)
    return {"threshold": thr, "threshold_source": f"{source}, the run's val set"}
